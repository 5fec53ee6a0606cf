"""The ``train`` flow: the training of ``models.training`` as Prefect tasks (one call each)."""

from __future__ import annotations

from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger, task

from cadio.cad.ingest import IngestConfig
from cadio.capture.examples import PROTOCOLS
from cadio.evidence.pairs import INPUTS
from cadio.sandbox import Limits
from cadio.workspace import Workspace
from models.evaluate import LEARNED
from models.training.completion import (
    Trained,
    evaluate_models,
    train_model,
    write_model_card,
)
from models.training.corpus import CorpusConfig
from models.training.prepare import Corpus, prepare_corpus

# ---------------------------------------------------------------- the train flow


@task(name="prepare-corpus")
def corpus_task(workspace: str, shared: str | None, variants: int, seed: int,
                workers: int) -> Corpus:
    """The training corpus: library with variants, shared parts, ingest, scenes, shots."""
    ingest_cfg = IngestConfig(limits=Limits(workers=workers, seconds=600))
    return prepare_corpus(Workspace(Path(workspace)), Path(shared) if shared else None,
                          variants, seed, ingest_cfg, CorpusConfig(seed=seed))


@task(name="train-model")
def train_task(workspace: str, method: str, protocol: str, steps: int, out: str) -> Trained:
    """One method on one protocol; the best checkpoint into ``out``."""
    return train_model(Workspace(Path(workspace)), method, protocol, steps, Path(out))


@task(name="evaluate-models")
def evaluate_task(workspace: str, out: str, run_dir: str) -> str:
    """Held-out scores of every method into the run's completion report."""
    evaluate_models(Workspace(Path(workspace)), Path(out), Path(run_dir))
    return run_dir


@task(name="relation-dataset")
def relation_dataset_task(workspace: str, completion: str, workers: int) -> dict[str, int]:
    """Labels of the corpus's pairs and the relation dataset completed by ``completion``."""
    from models.training.relations import build_dataset

    return build_dataset(Workspace(Path(workspace)), Path(completion),
                         Limits(workers=workers, seconds=600))


@task(name="train-relation-model")
def train_relation_task(workspace: str, method: str, name: str, steps: int,
                        out: str) -> dict[str, Any]:
    """One relation method on one input; the best checkpoint into ``out``."""
    from models.training.relations import train_relation_model

    return asdict(train_relation_model(Workspace(Path(workspace)), method, name, steps,
                                       Path(out)))


@task(name="evaluate-relations")
def evaluate_relations_task(workspace: str, out: str, run_dir: str, command: str,
                            config: dict[str, Any]) -> str:
    """Held-out relation report of every method and input, and the relation model card."""
    from models.training.relations import evaluate_relations, write_relation_card

    ws = Workspace(Path(workspace))
    evaluate_relations(ws, Path(out), Path(run_dir))
    return str(write_relation_card(ws, Path(out), Path(run_dir), command, config))


@flow(name="train")
def train(workspace: str = "train-workspace", shared: str | None = None, variants: int = 100,
          seed: int = 0, steps: int = 2000, methods: list[str] | None = None,
          protocols: list[str] | None = None, out: str | None = None,
          workers: int = 2, relation_steps: int = 1000,
          relation_out: str | None = None) -> dict[str, Any]:
    """Train the completion checkpoints, then the relation checkpoints on the same corpus, and
    write their held-out reports and model cards.

    Args:
        workspace: the training workspace (corpus, dataset, resumable snapshots, runs).
        shared: a folder of real STEP parts added to the corpus (split by part).
        variants: parametric variants per category of the sample library.
        steps: training steps per completion model (a rerun resumes unfinished ones).
        methods, protocols: which completion checkpoints (default: all three, both protocols).
        out: where the completion checkpoints and MODEL_CARD.md go (default: the workspace's
            ``checkpoints/completion``; ``mateqa ship completion`` makes them the default).
        workers: worker processes for the CAD and rendering work.
        relation_steps: training steps per relation model (0: no relation training).
        relation_out: where the relation checkpoints and their MODEL_CARD.md go (default: the
            workspace's ``checkpoints/relations``; ``mateqa ship relations`` ships them).
    """
    log = get_run_logger()
    ws = Workspace(Path(workspace).resolve())
    out = out or str(ws.checkpoints("completion"))
    relation_out = relation_out or str(ws.checkpoints("relations"))
    corpus = corpus_task(str(ws.root), shared, variants, seed, workers)
    log.info("corpus: %d parts %s, %d failed", corpus.parts, corpus.splits, corpus.failed)
    trained = [train_task(str(ws.root), m, p, steps, out)
               for p in protocols or list(PROTOCOLS) for m in methods or list(LEARNED)]
    for t in trained:
        log.info("%s/%s: best val IoU %.3f at step %d (%.0f s)", t.method, t.protocol,
                 t.val_iou, t.step, t.seconds)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    run_dir = ws.run_dir(stamp)
    evaluate_task(str(ws.root), out, str(run_dir))
    card = write_model_card(ws, Path(out), run_dir, f"prefect flow train(workspace={workspace!r}"
                            f", shared={shared!r}, variants={variants}, steps={steps})",
                            {"steps": steps, "variants": variants, "seed": seed}, corpus)
    result: dict[str, Any] = {"corpus": asdict(corpus), "trained": [asdict(t) for t in trained],
                              "report": str(run_dir), "card": str(card)}
    if relation_steps > 0:
        rows = relation_dataset_task(str(ws.root), out, workers)
        log.info("relation pair views per split: %s", rows)
        relations = [train_relation_task(str(ws.root), m, name, relation_steps, relation_out)
                     for name in INPUTS for m in ("ltn", "mlp")]
        rel_dir = ws.run_dir(f"relations-{stamp}")
        result["relations"] = relations
        result["relation_card"] = evaluate_relations_task(
            str(ws.root), relation_out, str(rel_dir),
            f"prefect flow train(workspace={workspace!r}, relation_steps={relation_steps})",
            {"steps": relation_steps, "seed": seed})
        result["relation_report"] = str(rel_dir)
    return result
