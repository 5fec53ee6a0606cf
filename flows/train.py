"""Training the learned stages: the corpus, the networks, their held-out scores, the model card.

``mateqa train completion`` runs these steps in the process (progress bars, no server); the
``train`` flow runs the same steps as Prefect tasks. Each step is one call into the packages:

1. corpus: the sample library with parametric variants (``cadio.samples``), plus the real
   parts of a shared STEP folder where given, ingested into the training workspace;
2. dataset: every distinct part rendered alone and cut into examples in both protocols
   (``cadio.capture.dataset``), split by part: the nightly's own sample parts are never
   trained on;
3. training of each learned method and protocol (``models``), checkpoints self-describing;
4. evaluation on the held-out parts beside the baselines (``models.evaluate``), written as the
   run's completion report and the model card.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from cadio.cad.ingest import IngestConfig, discover, ingest_files, mark_duplicates
from cadio.capture.dataset import (
    DatasetConfig,
    build_dataset,
    corpus_splits,
    read_index,
    unique_parts,
    write_index,
)
from cadio.catalog import read_catalog, to_frame, write_catalog
from cadio.samples.library import SampleConfig, generate_library
from cadio.workspace import Workspace

log = logging.getLogger(__name__)

Progress = Callable[[str], None]


@dataclass(frozen=True)
class Corpus:
    """Where the training examples are and how many parts each split holds."""

    dataset: str
    parts: int
    splits: dict[str, int]
    failed: int


def corpus_library(ws: Workspace) -> Path:
    """The training library: the sample library with its variants."""
    return ws.root / "library-train"


def prepare_corpus(ws: Workspace, shared: Path | None, variants: int, seed: int,
                   ingest_cfg: IngestConfig, dataset_cfg: DatasetConfig,
                   progress: Progress | None = None) -> Corpus:
    """Library with variants (+ shared parts), ingest, dataset. Reruns reuse every step."""
    library = corpus_library(ws)
    generate_library(library, SampleConfig(variants=variants, variant_seed=seed))
    found = discover(library) + (discover(shared) if shared is not None else [])
    rows = ingest_files(found, ws.root, ingest_cfg, read_catalog(ws.catalog))
    catalog = to_frame(mark_duplicates(rows))
    write_catalog(ws.catalog, catalog)
    parts = unique_parts(catalog)
    originals = str(library)

    def held_out(source: str) -> bool:  # the nightly's own sample parts: never trained on
        return source.startswith(originals) and "/variants/" not in source

    splits = corpus_splits(parts, held_out, seed)
    out = dataset_dir(ws)
    index = _reuse_or_build(parts, ws, out, splits, ingest_cfg, dataset_cfg, progress)
    ok = index[index["status"] == "ok"]
    per_split = ok.drop_duplicates("part_id")["split"].value_counts().to_dict()
    return Corpus(str(out), int(ok["part_id"].nunique()), {str(k): int(v)
                                                           for k, v in per_split.items()},
                  int((index["status"] != "ok").sum()))


def dataset_dir(ws: Workspace) -> Path:
    return ws.root / "datasets" / "completion"


def _reuse_or_build(parts: pd.DataFrame, ws: Workspace, out: Path, splits: dict[str, str],
                    ingest_cfg: IngestConfig, cfg: DatasetConfig,
                    progress: Progress | None) -> pd.DataFrame:
    """The dataset's index, building the parts it does not hold yet."""
    index_path = out / "index.parquet"
    old = read_index(index_path) if index_path.exists() else None
    done = set() if old is None else set(old.loc[old["status"] == "ok", "part_id"])
    todo = parts[~parts["part_id"].isin(done)]
    if old is not None and todo.empty:
        return old
    new = build_dataset(todo, ws.root, out, splits, cfg, ingest_cfg.limits, progress)
    merged = new if old is None else pd.concat([old[old["part_id"].isin(done)], new])
    merged = merged.reset_index(drop=True)
    write_index(index_path, merged)
    return merged


# ---------------------------------------------------------------- training and evaluation


@dataclass(frozen=True)
class Trained:
    """One trained checkpoint: where it went, its method and protocol, its best epoch."""

    path: str
    method: str
    protocol: str
    step: int
    val_iou: float
    seconds: float


def split_rows(ws: Workspace, protocol: str, split: str) -> pd.DataFrame:
    """The index rows of one protocol and split of the training dataset."""
    index = read_index(dataset_dir(ws) / "index.parquet")
    return index[(index["status"] == "ok") & (index["protocol"] == protocol)
                 & (index["split"] == split)]


def _files(ws: Workspace, rows: pd.DataFrame) -> list[Path]:
    return [dataset_dir(ws) / f for f in rows["file"]]


def train_model(ws: Workspace, method: str, protocol: str, steps: int, out_dir: Path,
                on_step: Callable[[int, int, dict[str, float]], None] | None = None,
                **overrides: Any) -> Trained:
    """Train one method on one protocol's training split; the best checkpoint by validation
    IoU goes to ``out_dir/completion-<method>-<protocol>.pt``, a resumable one beside the
    dataset (a rerun resumes it)."""
    from models.checkpoint import save_checkpoint
    from models.data import CompletionDataset
    from models.train import config_for, train_completion

    rows = split_rows(ws, protocol, "train")
    train, val = _files(ws, rows), _files(ws, split_rows(ws, protocol, "val"))
    parts = sorted(set(rows["part_id"]))
    cfg = config_for(method, **overrides)
    snapshot = ws.root / "models" / f"completion-{method}-{protocol}.resume.pt"
    clock = time.perf_counter()

    def progress(event: Any) -> None:
        if on_step is not None:
            on_step(event.step, event.steps, event.losses)
        if event.snapshot is not None:
            save_checkpoint(event.snapshot, snapshot)

    result = train_completion(
        cfg, CompletionDataset(paths=train), CompletionDataset(paths=val) if val else None,
        steps=steps, progress=progress, resume=snapshot if snapshot.exists() else None,
        data_info={"protocol": protocol, "train_parts": parts, "train_examples": len(train),
                   "val_examples": len(val), "dataset": str(dataset_dir(ws))})
    path = save_checkpoint(result.checkpoint, out_dir / f"completion-{method}-{protocol}.pt")
    best = result.checkpoint["metrics"]
    return Trained(str(path), method, protocol, int(result.checkpoint["step"]),
                   float(best.get("val_iou", float("nan"))), time.perf_counter() - clock)


def evaluate_models(ws: Workspace, models_dir: Path, run_dir: Path,
                    progress: Progress | None = None) -> pd.DataFrame:
    """Every held-out example of the training dataset, completed by every method and scored;
    the completion report and the registration table are written into ``run_dir``."""
    from models.evaluate import load_models, score_files
    from reports.completion import parts_frame, write_completion

    index = read_index(dataset_dir(ws) / "index.parquet")
    test = index[(index["status"] == "ok") & (index["split"] == "test")]
    category = dict(zip(test["part_id"], test["category"], strict=False))
    models = load_models(models_dir)
    scores = score_files([dataset_dir(ws) / f for f in test["file"]], models,
                         lambda pid: "test", lambda pid: category.get(pid, "unknown"), progress)
    parts = parts_frame(scores.parts)
    write_completion(run_dir, parts)
    pd.DataFrame(scores.registration).to_csv(run_dir / "completion_registration.csv",
                                             index=False)
    return parts
