"""The ``train`` flow: the steps of ``models.training.run`` as Prefect tasks, one call each, with
the same ``TrainConfig`` that ``mateqa train`` builds from its options."""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from prefect import flow, get_run_logger, task

from models.training import run
from models.training.completion import Trained
from models.training.config import TrainConfig
from models.training.prepare import Corpus
from models.training.relations import TrainedRelations

DEFAULT_TRAINING = TrainConfig()


@task(name="prepare-corpus")
def corpus_task(cfg: TrainConfig) -> Corpus:
    """The training corpus: library with variants, shared parts, ingest, scenes, shots."""
    return run.completion_corpus(cfg)


@task(name="train-model")
def train_task(cfg: TrainConfig, method: str, protocol: str) -> Trained:
    """One completion method on one protocol; the best checkpoint into the stage's folder."""
    return run.train_completion_network(cfg, method, protocol)


@task(name="evaluate-models")
def evaluate_task(cfg: TrainConfig, command: str, corpus: Corpus | None) -> run.Evaluated:
    """Held-out scores of every completion method, and the completion model card."""
    return run.evaluate_completion(cfg, command, corpus)


@task(name="relation-dataset")
def relation_dataset_task(cfg: TrainConfig) -> dict[str, int]:
    """The relation corpus where the workspace has none, its labels and the relation dataset
    completed by the workspace's completion network (else the shipped one)."""
    run.relation_corpus(cfg)
    return run.relation_dataset(cfg)


@task(name="train-relation-model")
def train_relation_task(cfg: TrainConfig, method: str, name: str) -> TrainedRelations:
    """One relation method on one input; the best checkpoint into the stage's folder."""
    return run.train_relation_network(cfg, method, name)


@task(name="evaluate-relations")
def evaluate_relations_task(cfg: TrainConfig, command: str) -> run.Evaluated:
    """Held-out relation report of every method and input, and the relation model card."""
    return run.evaluate_relation_networks(cfg, command)


@flow(name="train")
def train(config: TrainConfig = DEFAULT_TRAINING) -> dict[str, Any]:
    """Train the completion checkpoints, then the relation checkpoints on the same corpus (the
    stages of ``config.stages``), and write their held-out reports and model cards.

    Args:
        config: everything the run is given (``models.training.config.TrainConfig``: every
            field with its description and range; ``mateqa train`` makes the same object).
    """
    log = get_run_logger()
    command = f"prefect flow train(config={config.model_dump_json()})"
    result: dict[str, Any] = {"config": config.model_dump(mode="json")}
    if "completion" in config.stages:
        corpus = corpus_task(config)
        log.info("corpus: %d parts %s, %d failed", corpus.parts, corpus.splits, corpus.failed)
        trained = [train_task(config, m, p) for p in config.protocols
                   for m in config.methods_of_completion()]
        for t in trained:
            log.info("%s/%s: best val IoU %.3f at step %d (%.0f s)", t.method, t.protocol,
                     t.val_iou, t.step, t.seconds)
        done = evaluate_task(config, command, corpus)
        result.update(corpus=asdict(corpus), trained=[asdict(t) for t in trained],
                      completion=asdict(done))
    if "relations" in config.stages:
        rows = relation_dataset_task(config)
        log.info("relation pair views per split: %s", rows)
        relations = [train_relation_task(config, m, name)
                     for name in config.inputs_of_relations()
                     for m in config.methods_of_relations()]
        result.update(relations=[asdict(r) for r in relations],
                      relation_report=asdict(evaluate_relations_task(config, command)))
    return result
