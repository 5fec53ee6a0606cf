"""``mateqa train``: the completion checkpoints, then the relation networks (no Prefect), into
the training workspace, with the ``TrainConfig`` its options make (the ``train`` flow takes the
same object); ``mateqa ship``: those checkpoints over the shipped ones."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from cadio.errors import InputFileError
from flows.cli_cad import progress

if TYPE_CHECKING:
    from models.training.config import TrainConfig


def cmd_train(args: argparse.Namespace) -> int:
    import torch

    torch.set_num_threads(args.config.threads)
    command = "mateqa " + shlex.join(args.argv)
    if args.stage == "relations":
        return _train_relations(args.config, command)
    return _train_completion(args.config, command)


def _train_completion(cfg: TrainConfig, command: str) -> int:
    from models.training import run

    try:
        with progress("corpus parts", None) as advance:
            corpus = run.completion_corpus(cfg, advance)
    except (InputFileError, ValueError) as exc:
        print(f"mateqa train: {exc}", file=sys.stderr)
        return 2
    print(f"corpus: {corpus.parts} parts {corpus.splits}, {corpus.failed} failed")
    for protocol in cfg.protocols:
        for method in cfg.methods_of_completion():
            with progress(f"{method}/{protocol}", cfg.completion_steps) as advance:
                trained = run.train_completion_network(cfg, method, protocol,
                                                       on_step=lambda *a: advance(""))
            print(f"{method}/{protocol}: best val IoU {trained.val_iou:.3f} at step "
                  f"{trained.step} ({trained.seconds:.0f} s) -> {trained.path}")
    done = run.evaluate_completion(cfg, command, corpus)
    print(Path(done.report).read_text())
    print(f"model card: {done.card}")
    return _trained(cfg, "completion")


def _train_relations(cfg: TrainConfig, command: str) -> int:
    from models.training import run

    try:
        with progress("corpus of pairs", None) as advance:
            built = run.relation_corpus(cfg, advance)
        if built is not None:
            print(f"corpus of the relation networks: {built.parts} parts {built.splits}, "
                  f"shots {built.shots}, {built.failed} failed")
        with progress("labelled shots", None) as advance:
            rows = run.relation_dataset(cfg, advance)
    except (InputFileError, FileNotFoundError, ValueError) as exc:
        print(f"mateqa train relations: {exc}", file=sys.stderr)
        return 2
    print(f"pair views per split {rows}")
    for name in cfg.inputs_of_relations():
        for method in cfg.methods_of_relations():
            with progress(f"{method}/{name}", cfg.relation_steps) as advance:
                trained = run.train_relation_network(cfg, method, name,
                                                     on_step=lambda: advance(""))
            print(f"{method}/{name}: best val accuracy {trained.val_accuracy:.4f} at step "
                  f"{trained.step} ({trained.seconds:.0f} s) -> {trained.path}")
    done = run.evaluate_relation_networks(cfg, command)
    print(Path(done.report).read_text())
    print(f"model card: {done.card}")
    return _trained(cfg, "relations")


def _trained(cfg: TrainConfig, stage: str) -> int:
    """Say where the checkpoints are, how a night tries them and how to ship them."""
    from models.training.run import out_dir

    out = out_dir(cfg, stage)
    option = {"completion": "--completion-models", "relations": "--relation-models"}
    print(f"checkpoints in {out}: `mateqa nightly {option[stage]} {out}` tries them; "
          f"`mateqa ship {stage} --workspace {cfg.workspace}` makes them the default")
    return 0


def cmd_ship(args: argparse.Namespace) -> int:
    from models.checkpoint import ship_checkpoints
    from models.errors import CheckpointError
    from models.evaluate import SHIPPED
    from models.relate import SHIPPED_RELATIONS
    from models.training.config import TrainConfig
    from models.training.run import out_dir

    out = str(args.out) if args.out else None
    cfg = TrainConfig.model_validate({"workspace": str(args.workspace), (
        "completion_out" if args.stage == "completion" else "relation_out"): out})
    trained = out_dir(cfg, args.stage)
    shipped = {"completion": SHIPPED, "relations": SHIPPED_RELATIONS}[args.stage]
    try:
        files = ship_checkpoints(trained, shipped)
    except CheckpointError as exc:
        print(f"mateqa ship: {exc}", file=sys.stderr)
        return 2
    print(f"shipped {len(files)} files of {trained} into {shipped}")
    return 0
