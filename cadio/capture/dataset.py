"""The shape-completion dataset: every catalog part rendered alone and cut into examples.

Each part is posed (``examples.part_pose``), rendered from ``n_views`` views spread over the
paper's camera circle, and turned into examples (``examples.view_sets``): single views and
sequences, in both protocols, each with its target. One crash-isolated worker job per part
(``cadio.sandbox``): a part that fails is a row with its reason and the others go on. The
index (``index.parquet``) lists one row per example file with its part, category, split,
protocol, views and the share of the part its cube holds. Splits are by part, never by view.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from cadio.capture.examples import (
    ORACLE,
    PROTOCOLS,
    ExampleConfig,
    observed_example,
    oracle_example,
    part_pose,
    render_part_views,
    view_sets,
    with_truth,
    write_example,
)
from cadio.capture.noise import NoiseConfig
from cadio.capture.render import CaptureConfig
from cadio.sandbox import Job, Limits, run_isolated
from cadio.truth.scenes import assign_splits
from cadio.workspace import Workspace, atomic_path, read_mesh

log = logging.getLogger(__name__)

INDEX = "index.parquet"
INDEX_COLUMNS = ("file", "part_id", "category", "split", "protocol", "n_views", "views",
                 "view_deg", "coverage", "status", "error")


@dataclass(frozen=True)
class DatasetConfig:
    """What each part contributes. The defaults give 8 single views and sequences of 2, 4, 8
    from 8 rendered views, in both protocols: 22 examples a part."""

    example: ExampleConfig = field(default_factory=ExampleConfig)
    n_views: int = 8
    singles: int = 8
    lengths: tuple[int, ...] = (2, 4, 8)
    protocols: tuple[str, ...] = PROTOCOLS
    noise: bool = False

    def capture(self) -> CaptureConfig:
        return CaptureConfig(noise=NoiseConfig() if self.noise else None)

    def rendered(self) -> list[int]:
        """The rendered view indices of the 125-view circle, spread evenly."""
        total = self.capture().n_views
        return [round(i * total / self.n_views) % total for i in range(self.n_views)]


@dataclass(frozen=True)
class PartJob:
    """One part for a dataset worker."""

    part_id: str
    category: str
    split: str
    mesh_path: str
    out_dir: str
    cfg: DatasetConfig


@dataclass(frozen=True)
class IndexRow:
    """One example file of the dataset (or one part that gave none, with the reason)."""

    file: str
    part_id: str
    category: str
    split: str
    protocol: str = ""
    n_views: int = 0
    views: tuple[int, ...] = ()
    view_deg: float = float("nan")
    coverage: float = float("nan")
    status: str = "ok"
    error: str = ""


def example_job(job: PartJob) -> list[IndexRow]:
    """Render one part and write its examples (the job of an isolated worker)."""
    cfg, mesh = job.cfg, read_mesh(Path(job.mesh_path))
    views, part_to_world = render_part_views(mesh, part_pose(job.part_id, mesh),
                                             cfg.rendered(), cfg.capture())
    if not views:
        raise ValueError("no view saw enough of the part")
    rows = []
    for chosen in view_sets(len(views), min(cfg.singles, len(views)), cfg.lengths):
        seq = [views[i] for i in chosen]
        for protocol in cfg.protocols:
            if protocol == ORACLE:
                example = oracle_example(seq, mesh, part_to_world, cfg.example)
            else:
                example = observed_example(seq, cfg.example)
            example = with_truth(example, mesh, part_to_world, cfg.example)
            name = f"{job.part_id}-{protocol[:3]}-{'-'.join(map(str, example.views))}.npz"
            path = Path(job.out_dir) / protocol / name
            meta = {"part_id": job.part_id, "category": job.category, "split": job.split}
            write_example(path, example, meta)
            rows.append(IndexRow(
                file=f"{protocol}/{name}", part_id=job.part_id, category=job.category,
                split=job.split, protocol=protocol, n_views=len(seq), views=example.views,
                view_deg=example.azimuths[0], coverage=example.coverage))
    return rows


def build_dataset(parts: pd.DataFrame, workspace: Path, out_dir: Path,
                  splits: Mapping[str, str], cfg: DatasetConfig, limits: Limits | None = None,
                  on_part: Callable[[str], None] | None = None) -> pd.DataFrame:
    """Examples of every part into ``out_dir`` and their index (also written there).

    Args:
        parts: catalog rows (ok parts) with part_id and category.
        splits: part id -> "train", "val" or "test" (by part).
        on_part: called with each part id once it is done (progress bars).
    """
    ws = Workspace(Path(workspace))
    jobs = [Job(str(r.part_id), PartJob(str(r.part_id), str(r.category),
                                        splits.get(str(r.part_id), "test"),
                                        str(ws.mesh(str(r.part_id))), str(out_dir), cfg))
            for r in parts.itertuples()]
    rows: list[IndexRow] = []
    for outcome in run_isolated(example_job, jobs, limits or Limits()):
        job = outcome.job.payload
        if on_part is not None:
            on_part(job.part_id)
        if outcome.result is not None:
            rows.extend(outcome.result)
            continue
        reason = outcome.error.reason if outcome.error is not None else "no result"
        log.warning("part %s: %s", job.part_id, reason)
        rows.append(IndexRow("", job.part_id, job.category, job.split, status="failed",
                             error=reason))
    index = index_frame(rows)
    write_index(out_dir / INDEX, index)
    return index


def index_frame(rows: Sequence[IndexRow]) -> pd.DataFrame:
    frame = pd.DataFrame([asdict(r) for r in rows], columns=list(INDEX_COLUMNS))
    frame["views"] = [list(v) for v in frame["views"]]
    return frame.sort_values(["part_id", "protocol", "n_views", "file"]).reset_index(drop=True)


def write_index(path: Path, index: pd.DataFrame) -> None:
    with atomic_path(path) as tmp:
        index.to_parquet(tmp, index=False)


def read_index(path: Path) -> pd.DataFrame:
    return pd.read_parquet(path)


def unique_parts(catalog: pd.DataFrame) -> pd.DataFrame:
    """The catalog's ok parts, one per distinct geometry: assemblies repeat their bolts and
    nuts, and a repeated part would sit in one split many times (size and volume identical to
    a micrometre and a cubic millimetre count as the same geometry)."""
    ok = catalog[catalog["status"] == "ok"].copy()
    extent = [tuple(sorted(np.round(np.subtract(hi, lo), 3)))
              for lo, hi in zip(ok["bbox_min"], ok["bbox_max"], strict=True)]
    ok["_key"] = [f"{v:.0f}|{f}|{e}" for v, f, e in zip(ok["volume"], ok["n_faces"], extent,
                                                         strict=True)]
    return ok.sort_values("part_id").drop_duplicates("_key").drop(columns="_key")


def corpus_splits(parts: pd.DataFrame, held_out: Callable[[str], bool], seed: int = 0,
                  val_fraction: float = 0.1, test_fraction: float = 0.2) -> dict[str, str]:
    """Split of each part (by part, from a hash of the seed and the part id); parts whose
    source file ``held_out`` names (the nightly's own sample library) are always "test"."""
    drawn = assign_splits(sorted(map(str, parts["part_id"])), seed, val_fraction, test_fraction)
    return {str(pid): "test" if held_out(str(src)) else drawn[str(pid)]
            for pid, src in zip(parts["part_id"], parts["source"], strict=True)}
