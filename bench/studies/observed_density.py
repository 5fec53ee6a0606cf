"""Whether one view's observed points carry the CAD's concentric and coincident mates at all.

The relation stage keeps 600 observed points per part and view (``points.npz``), and its pair
evidence (``cadio.evidence.pair_features``) is measured on them. The captures hold many more: a
part of a held-out assembly shows thousands of pixels. The symmetric mates are decided at 1 mm,
and the night's networks call many pairs mates that are not (a ring's cage segments 1.6 mm
inside it, nuts 1.6 mm off a flange). This asks whether the missing precision is in the pixels
at all: for every view of every pair of the held-out assemblies of a night's workspace, it
measures the observed contact gap (``gap_mm``: the nearest distance between the two parts'
observed points, as the pair evidence has it) at each density asked for (``0``: every observed
point), and compares the CAD's mates with the pairs the night's ``ltn`` on ``completed`` called
mates wrongly: their medians, the share within the mates' 1 mm, and the AUC of "the smaller gap
is the mate" (0.5: the gap cannot tell them apart). A mate's faces touch, but the faces of a
shaft in a bore are hidden by the shaft itself.

Usage:
    .venv/bin/python bench/studies/observed_density.py --workspace heldout/ws [--points 600 3000 0]

The workspace is a night's (``python -m models.training.heldout``, then ``mateqa
nightly``). Nothing is asserted.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from cadio.capture.examples import frame_supports, part_views
from cadio.catalog import read_catalog
from cadio.evidence.pair_features import PAIR_FEATURES, pair_features_many
from cadio.evidence.pairs import DEFAULT_PAIRS, capture_pairs, evidence_cloud
from cadio.recordings.mcap_io import read_capture, read_scene_meta
from cadio.records import FloatArray
from cadio.workspace import Workspace
from models.relation_inputs.partial import observed_clouds
from models.relation_inputs.truth import truth_clouds

MATES = {8: "concentric", 9: "coincident"}
TOUCH_MM = 1.0  # the mates' faces are within this of each other

STOCK = {"truth": truth_clouds, "partial": observed_clouds}  # the inputs read here


def observed_clouds(capture: Path) -> dict[tuple[str, int], FloatArray]:
    """(part id, view) -> every observed point of that part in that view (world metres)."""
    meta = read_scene_meta(capture) or {}
    frames = list(read_capture(capture))
    labels = [f.instance for f in frames if f.instance is not None]
    if len(labels) != len(frames):  # a recording without instance ids: no part to tell apart
        return {}
    supports = frame_supports(frames, labels)
    return {(str(part["part_id"]), v.view): v.points for part in meta.get("parts", [])
            for v in part_views(frames, labels, int(part["instance_id"]), supports)}


def observed_gaps(ws: Workspace, points: list[int]
                  ) -> tuple[pd.DataFrame, dict[int, npt.NDArray[np.float32]]]:
    """(one row per pair view of the workspace's assembly captures: scene, view, part_a,
    part_b, labels; density -> (V,) the observed contact gap, mm)."""
    catalog = read_catalog(ws.catalog)
    categories = dict(zip(catalog["part_id"].astype(str), catalog["category"].astype(str),
                          strict=True))
    rows: list[dict[str, object]] = []
    gaps: dict[int, list[npt.NDArray[np.float32]]] = {n: [] for n in points}
    column = PAIR_FEATURES.index("gap_mm")
    for capture in sorted((ws.root / "captures").glob("assembly-*.mcap")):
        clouds = observed_clouds(capture)
        views = capture_pairs(capture, ws, categories, DEFAULT_PAIRS, STOCK)
        mm = np.array([1.0 / v.scale_m_per_mm for v in views])
        keys = [((v.part_a, v.view), (v.part_b, v.view)) for v in views]
        for n in points:
            pairs = [tuple(np.asarray(evidence_cloud(clouds[k], n) if n else clouds[k],
                                      dtype=np.float32) for k in key) for key in keys]
            gaps[n].append(pair_features_many(pairs, mm, keys)[:, column])
        rows += [{"scene": v.scene, "view": v.view, "part_a": v.part_a, "part_b": v.part_b,
                  "labels": v.labels} for v in views]
    return pd.DataFrame(rows), {n: np.concatenate(g) for n, g in gaps.items()}


def night_said(run: Path, views: pd.DataFrame, relation: str) -> npt.NDArray[np.bool_]:
    """(V,) bool: the night's ltn on completed called the view's pair ``relation``."""
    path = run / "relations_pairs.parquet"
    if not path.is_file():
        return np.zeros(len(views), dtype=bool)
    rows = pd.read_parquet(path)
    rows = rows[(rows["input"] == "completed") & (rows["method"] == "ltn")
                & (rows["relation"] == relation)]
    said = {(r.scene, int(r.view), r.part_a, r.part_b): bool(r.predicted)
            for r in rows.itertuples()}
    return np.array([said.get((r.scene, int(r.view), r.part_a, r.part_b), False)
                     for r in views.itertuples()], dtype=bool)


def auc(positive: npt.ArrayLike, negative: npt.ArrayLike) -> float:
    """P(a positive scores above a negative), ties counting half."""
    p, q = np.asarray(positive)[:, None], np.asarray(negative)[None, :]
    return float(np.mean((p > q) + 0.5 * (p == q)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workspace", type=Path, required=True)
    ap.add_argument("--points", type=int, nargs="+", default=[600, 3000, 0])
    args = ap.parse_args()
    ws = Workspace(args.workspace)
    clock = time.perf_counter()
    views, gaps = observed_gaps(ws, args.points)
    labels = np.stack(views["labels"].to_list())
    run = ws.root / "runs" / "latest"
    said = {col: night_said(run, views, name) for col, name in MATES.items()}
    print(f"{len(views)} pair views of {views['scene'].nunique()} assemblies, "
          f"{time.perf_counter() - clock:.0f} s")
    print("| points per part | relation | CAD mates | night's false mates | median gap, mates / "
          f"false (mm) | within {TOUCH_MM:g} mm, mates / false | AUC |")
    print("|---|---|---|---|---|---|---|")
    for n in args.points:
        gap = gaps[n]
        for col, name in MATES.items():
            mate, wrong = labels[:, col], said[col] & ~labels[:, col]
            if not mate.any() or not wrong.any():
                continue
            print(f"| {n or 'every'} | {name} | {mate.sum()} | {wrong.sum()} | "
                  f"{np.median(gap[mate]):.2f} / {np.median(gap[wrong]):.2f} | "
                  f"{np.mean(gap[mate] <= TOUCH_MM):.2f} / {np.mean(gap[wrong] <= TOUCH_MM):.2f}"
                  f" | {auc(-gap[mate], -gap[wrong]):.3f} |")


if __name__ == "__main__":
    main()
