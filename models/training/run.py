"""A training run of a ``TrainConfig``, step by step, without Prefect.

``mateqa train STAGE`` runs these steps in its process (with progress bars) and the ``train``
flow runs the same steps as tasks, each one call with the same config: the corpus, each
network, the held-out evaluation and the model card, for the completion networks and then the
relation networks. Every step resumes what a stopped run left (``models.training.prepare``,
the networks' snapshots, the labels and the dataset's stamp).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from cadio.cad.ingest import IngestConfig
from cadio.capture.examples import OBSERVED, ExampleConfig
from cadio.sandbox import Limits
from cadio.tolerances import DEFAULT_TOLERANCES
from cadio.workspace import Workspace
from models.training.completion import (
    Trained,
    evaluate_models,
    train_model,
    write_model_card,
)
from models.training.config import TrainConfig
from models.training.corpus import KINDS, CorpusConfig
from models.training.prepare import (
    Corpus,
    CorpusPlan,
    Progress,
    dataset_dir,
    prepare_corpus,
)
from models.training.relations import (
    TrainedRelations,
    build_dataset,
    evaluate_relations,
    train_relation_model,
    write_relation_card,
)

# A CAD job of the corpus (a shot, a label) may take this long before its worker is killed.
JOB_SECONDS = 600.0


def workspace(cfg: TrainConfig) -> Workspace:
    return Workspace(Path(cfg.workspace).resolve())


def limits(cfg: TrainConfig) -> Limits:
    import os

    return Limits(workers=cfg.workers or os.cpu_count() or 1, seconds=JOB_SECONDS)


def out_dir(cfg: TrainConfig, stage: str) -> Path:
    """Where a stage's checkpoints and card go: its ``*_out``, else the workspace's."""
    given = cfg.completion_out if stage == "completion" else cfg.relation_out
    return Path(given or workspace(cfg).checkpoints(stage)).resolve()


def _shared(cfg: TrainConfig) -> Path | None:
    # resolved: the corpus's split draw keys each file by its path as given, and the shipped
    # checkpoints' corpus was given an absolute one (``models.training.heldout`` relies on it)
    return Path(cfg.shared).resolve() if cfg.shared else None


def corpus_plan(cfg: TrainConfig, kinds: tuple[str, ...] = KINDS) -> CorpusPlan:
    """What the configuration makes the corpus of."""
    return CorpusPlan(_shared(cfg), cfg.variants, cfg.seed, cfg.pairs_per_relation,
                      contact_pairs=cfg.contact_pairs, clearance_pairs=cfg.clearance_pairs,
                      kinds=kinds)


def _example(cfg: TrainConfig) -> ExampleConfig:
    return ExampleConfig(n_in=cfg.grids[0], n_out=cfg.grids[1],
                         grid_margin=DEFAULT_TOLERANCES.grid_margin)


def completion_corpus(cfg: TrainConfig, progress: Progress | None = None) -> Corpus:
    """The whole corpus (every kind of shot, single views and sequences, both protocols)."""
    return prepare_corpus(workspace(cfg), corpus_plan(cfg), IngestConfig(limits=limits(cfg)),
                          CorpusConfig(example=_example(cfg), seed=cfg.seed), progress)


def relation_corpus(cfg: TrainConfig, progress: Progress | None = None) -> Corpus | None:
    """The part of the corpus the relation networks read, where the workspace has no corpus
    yet: the same library, splits, scenes and shot ids, but only the pair and assembly shots
    and their single observed views (on two cores about 20 min against 104 for the whole);
    None when a corpus is there. Stamped with its own configuration, so ``completion`` refuses
    to train on it."""
    if (dataset_dir(workspace(cfg)) / "index.parquet").exists():
        return None
    corpus_cfg = CorpusConfig(example=_example(cfg), lengths=(), protocols=(OBSERVED,),
                              seed=cfg.seed)
    return prepare_corpus(workspace(cfg), corpus_plan(cfg, tuple(k for k in KINDS
                                                                 if k != "alone")),
                          IngestConfig(limits=limits(cfg)), corpus_cfg, progress)


def train_completion_network(cfg: TrainConfig, method: str, protocol: str,
                             on_step: Callable[[int, int, dict[str, float]], None] | None = None
                             ) -> Trained:
    """One completion method on one protocol of the corpus (a rerun resumes it)."""
    return train_model(workspace(cfg), method, protocol, cfg.completion_steps,
                       out_dir(cfg, "completion"), on_step=on_step,
                       rates={"lr": cfg.lr, "lr_d": cfg.lr_critic},
                       n_in=cfg.grids[0], n_out=cfg.grids[1])


@dataclass(frozen=True)
class Evaluated:
    """A stage's held-out report (its run folder and Markdown) and its model card."""

    run_dir: str
    report: str
    card: str


def evaluate_completion(cfg: TrainConfig, command: str, corpus: Corpus | None = None
                        ) -> Evaluated:
    """Every completion method on the held-out split beside the baselines, and the card."""
    ws, out = workspace(cfg), out_dir(cfg, "completion")
    run_dir = ws.run_dir(time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()))
    evaluate_models(ws, out, run_dir)
    card = write_model_card(ws, out, run_dir, command, _knobs(cfg, "completion"), corpus)
    return Evaluated(str(run_dir), str(run_dir / "completion.md"), str(card))


def completion_for_relations(cfg: TrainConfig) -> Path:
    """The completion checkpoints the relation dataset is completed with: those trained in
    the workspace, else the shipped ones."""
    from models.evaluate import SHIPPED

    trained = out_dir(cfg, "completion")
    return trained if any(trained.glob("*.pt")) else SHIPPED


def relation_dataset(cfg: TrainConfig, progress: Progress | None = None) -> dict[str, int]:
    """The labelled pairs of the corpus in every trained input; pair views per split.

    Raises:
        FileNotFoundError: the workspace has no corpus (``relation_corpus`` builds one).
    """
    if not (dataset_dir(workspace(cfg)) / "index.parquet").exists():
        raise FileNotFoundError(f"{dataset_dir(workspace(cfg))}: no corpus")
    return build_dataset(workspace(cfg), completion_for_relations(cfg), limits(cfg), progress)


def train_relation_network(cfg: TrainConfig, method: str, name: str,
                           on_step: Callable[[], None] | None = None) -> TrainedRelations:
    """One relation network on one input, with its joint head."""
    return train_relation_model(workspace(cfg), method, name, cfg.relation_steps,
                                out_dir(cfg, "relations"), on_step=on_step)


def evaluate_relation_networks(cfg: TrainConfig, command: str) -> Evaluated:
    """Every relation method on every input of the test split, and the card."""
    ws, out = workspace(cfg), out_dir(cfg, "relations")
    run_dir = ws.run_dir(time.strftime("relations-%Y%m%dT%H%M%SZ", time.gmtime()))
    report = evaluate_relations(ws, out, run_dir)
    card = write_relation_card(ws, out, run_dir, command, _knobs(cfg, "relations"))
    return Evaluated(str(run_dir), str(report), str(card))


def _knobs(cfg: TrainConfig, stage: str) -> dict[str, object]:
    """The training knobs a stage's card records beside each checkpoint's own config."""
    shared = {"seed": cfg.seed, "variants": cfg.variants,
              "pairs_per_relation": cfg.pairs_per_relation,
              "contact_pairs": cfg.contact_pairs, "clearance_pairs": cfg.clearance_pairs,
              "threads": cfg.threads}
    if stage == "completion":
        return {"steps": cfg.completion_steps, **shared}
    return {"steps": cfg.relation_steps, **shared}

