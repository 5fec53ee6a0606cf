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
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

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
