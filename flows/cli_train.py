"""``mateqa train``: the completion checkpoints, then the relation networks (no Prefect), into
the training workspace; ``mateqa ship``: those checkpoints over the shipped ones."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from cadio.errors import InputFileError
from flows.cli_cad import progress

if TYPE_CHECKING:
    from cadio.workspace import Workspace


def cmd_train(args: argparse.Namespace) -> int:
    if args.stage == "relations":
        return _cmd_train_relations(args)
    import shlex
    import time

    import torch

    from cadio.cad.ingest import IngestConfig
    from cadio.capture.examples import ExampleConfig
    from cadio.sandbox import Limits
    from cadio.workspace import Workspace
    from models.training.completion import (
        evaluate_models,
        train_model,
        write_model_card,
    )
    from models.training.corpus import CorpusConfig
    from models.training.prepare import prepare_corpus

    torch.set_num_threads(args.threads)
    ws = Workspace(args.workspace.resolve())
    out = train_out(args, ws)
    ingest_cfg = IngestConfig(limits=Limits(workers=args.workers, seconds=600),
                              tolerances=args.tolerances)
    try:
        with progress("corpus parts", None) as advance:
            corpus = prepare_corpus(ws, args.shared, args.variants, args.seed, ingest_cfg,
                                    CorpusConfig(example=ExampleConfig(
                n_in=args.grids[0], n_out=args.grids[1],
                grid_margin=args.tolerances.grid_margin), seed=args.seed), advance,
                pairs_per_relation=args.pairs_per_relation, contact_pairs=args.contact_pairs,
                clearance_pairs=args.clearance_pairs)
    except (InputFileError, ValueError) as exc:
        print(f"mateqa train: {exc}", file=sys.stderr)
        return 2
    print(f"corpus: {corpus.parts} parts {corpus.splits}, {corpus.failed} failed")
    for protocol in args.protocols:
        for method in args.methods or ["gan_lstm", "ae", "r2n2"]:
            with progress(f"{method}/{protocol}", args.steps) as advance:
                trained = train_model(ws, method, protocol, args.steps, out,
                                      on_step=lambda *a: advance(""),
                                      rates={"lr": args.lr, "lr_d": args.lr_critic},
                                      n_in=args.grids[0], n_out=args.grids[1])
            print(f"{method}/{protocol}: best val IoU {trained.val_iou:.3f} at step "
                  f"{trained.step} ({trained.seconds:.0f} s) -> {trained.path}")
    run_dir = ws.run_dir(time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()))
    evaluate_models(ws, out, run_dir)
    command = "mateqa " + shlex.join(args.argv)
    card = write_model_card(ws, out, run_dir, command,
                            {"steps": args.steps, "variants": args.variants, "seed": args.seed,
                             "threads": args.threads,
                             "pairs_per_relation": args.pairs_per_relation,
                             "contact_pairs": args.contact_pairs,
                             "clearance_pairs": args.clearance_pairs}, corpus)
    print(Path(run_dir / "completion.md").read_text())
    print(f"model card: {card}")
    return _trained(args, out)


def _cmd_train_relations(args: argparse.Namespace) -> int:
    import shlex
    import time

    import torch

    from cadio.sandbox import Limits
    from cadio.workspace import Workspace
    from models.evaluate import SHIPPED
    from models.training.relations import (
        build_dataset,
        evaluate_relations,
        train_relation_model,
        write_relation_card,
    )

    torch.set_num_threads(args.threads)
    ws = Workspace(args.workspace.resolve())
    out = train_out(args, ws)
    completion = ws.checkpoints("completion")  # trained in this workspace, else the shipped
    completion = completion if any(completion.glob("*.pt")) else SHIPPED
    try:
        with progress("labelled shots", None) as advance:
            rows = build_dataset(ws, completion, Limits(workers=args.workers, seconds=600),
                                 advance)
    except (FileNotFoundError, ValueError) as exc:
        print(f"mateqa train relations: {exc} (run mateqa train completion in this workspace "
              "first)", file=sys.stderr)
        return 2
    print(f"pair views per split {rows}")
    for name in args.inputs:
        for method in args.methods or ["ltn", "mlp"]:
            with progress(f"{method}/{name}", args.steps) as advance:
                trained = train_relation_model(ws, method, name, args.steps, out,
                                               on_step=lambda: advance(""))
            print(f"{method}/{name}: best val accuracy {trained.val_accuracy:.4f} at step "
                  f"{trained.step} ({trained.seconds:.0f} s) -> {trained.path}")
    run_dir = ws.run_dir(time.strftime("relations-%Y%m%dT%H%M%SZ", time.gmtime()))
    report = evaluate_relations(ws, out, run_dir)
    card = write_relation_card(ws, out, run_dir, "mateqa " + shlex.join(args.argv),
                               {"steps": args.steps, "seed": args.seed,
                                "pairs_per_relation": args.pairs_per_relation})
    print(report.read_text())
    print(f"model card: {card}")
    return _trained(args, out)


def train_out(args: argparse.Namespace, ws: Workspace) -> Path:
    """Where ``mateqa train`` writes: ``--out``, else the training workspace's checkpoints."""
    return Path(args.out or ws.checkpoints(args.stage)).resolve()


def _trained(args: argparse.Namespace, out: Path) -> int:
    """Say where the checkpoints are, how a night tries them and how to ship them."""
    option = {"completion": "--completion-models", "relations": "--relation-models"}
    print(f"checkpoints in {out}: `mateqa nightly {option[args.stage]} {out}` tries them; "
          f"`mateqa ship {args.stage} --workspace {args.workspace}` makes them the default")
    return 0


def cmd_ship(args: argparse.Namespace) -> int:
    from cadio.workspace import Workspace
    from models.checkpoint import ship_checkpoints
    from models.errors import CheckpointError
    from models.evaluate import SHIPPED
    from models.relate import SHIPPED_RELATIONS

    trained = train_out(args, Workspace(args.workspace.resolve()))
    shipped = {"completion": SHIPPED, "relations": SHIPPED_RELATIONS}[args.stage]
    try:
        files = ship_checkpoints(trained, shipped)
    except CheckpointError as exc:
        print(f"mateqa ship: {exc}", file=sys.stderr)
        return 2
    print(f"shipped {len(files)} files of {trained} into {shipped}")
    return 0
