"""The relation networks' dataset: pair views of a corpus's captures, split by part.

``build_relation_dataset`` turns every capture of a training workspace into pair views
(``cadio.capture.pairs``, with the completion network's shapes for the ``completed`` input) and
writes one ``<split>.npz`` per split: for each input the points in the observer's frame
(N, 2, k, 3) float16, the labels (N, 10) bool, and which scene, view, parts and category each
row is. A scene joins parts of one split only, and the split of every part is the completion
dataset's, so the completion network never saw a relation test part either.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from cadio.capture.pairs import DEFAULT_PAIRS, INPUTS, PairConfig, PairView, capture_pairs
from cadio.errors import CaptureError
from cadio.workspace import Workspace, atomic_write
from models.relate import completions_of
from models.relations_train import RelationData
from models.train import Model

log = logging.getLogger(__name__)

META = ("scene", "view", "part_a", "part_b", "category", "near_boundary", "scale_m_per_mm")


@dataclass(frozen=True)
class RelationSplit:
    """One split of the dataset: inputs (name -> (N, 2, k, 3) float32 observer frame), labels
    (N, 10) bool and the rows' provenance (``META`` columns)."""

    inputs: dict[str, npt.NDArray[np.float32]]
    labels: npt.NDArray[np.bool_]
    meta: pd.DataFrame

    def data(self, name: str, rows: npt.NDArray[np.bool_] | None = None) -> RelationData:
        keep = np.ones(len(self.labels), dtype=bool) if rows is None else rows
        return RelationData(points=self.inputs[name][keep], labels=self.labels[keep])


def build_relation_dataset(captures: Sequence[Path], ws: Workspace,
                           categories: Mapping[str, str], splits: Mapping[str, str],
                           completion: Model | None, out_dir: Path,
                           cfg: PairConfig = DEFAULT_PAIRS,
                           progress: Callable[[str], None] | None = None) -> dict[str, int]:
    """Write ``<split>.npz`` for every split of the captures' pair views; rows per split.

    Pair views missing an input (a part the completion could not place) are left out, so all
    inputs of a row are the same pair in the same view.
    """
    by_split: dict[str, list[PairView]] = {}
    for path in captures:
        try:
            views = capture_pairs(path, ws, categories, cfg, completions_of(path, ws, completion))
        except (OSError, ValueError, KeyError, CaptureError) as exc:
            log.warning("%s: %s", path.name, exc)
            continue
        for v in views:
            if all(name in v.points for name in INPUTS):
                by_split.setdefault(splits.get(v.part_a, "test"), []).append(v)
        if progress is not None:
            progress(path.name)
    out_dir.mkdir(parents=True, exist_ok=True)
    for split, views in by_split.items():
        write_split(out_dir / f"{split}.npz", views)
    return {s: len(v) for s, v in sorted(by_split.items())}


def write_split(path: Path, views: Sequence[PairView]) -> None:
    """One split's arrays (points as float16: a millimetre in a metre-sized scene survives)."""
    arrays: dict[str, Any] = {
        f"points_{n}": np.stack([v.observer_points(n) for v in views]).astype(np.float16)
        for n in INPUTS}
    arrays["labels"] = np.stack([v.labels for v in views])
    for col in META:
        arrays[col] = np.array([getattr(v, col) for v in views])
    with atomic_write(path) as fh:
        np.savez(fh, **arrays)


def read_split(path: Path) -> RelationSplit:
    """A split written by ``write_split``."""
    with np.load(path) as z:
        inputs = {n: z[f"points_{n}"].astype(np.float32) for n in INPUTS}
        meta = pd.DataFrame({col: z[col] for col in META})
        return RelationSplit(inputs, z["labels"].astype(bool), meta)
