"""How well the point evidence finds the dominant plane directions that the truth's parallel and
perpendicular rest on.

The truth calls a pair parallel when both parts' dominant plane directions (the direction
carrying at least 1.5 times the planar face area of the runner-up, from the B-rep) lie within
the tolerance and the pair is not coincident; perpendicular at 90 degrees. The relation
networks and ``geometric`` see instead ``dominant_direction`` of the points: planes fitted to
them, each direction weighted by the points its planes hold. This reads a relation dataset
split (``datasets/relations/<split>.npz``), recomputes that evidence for the clear pairs of one
input (``truth``: exact CAD surface samples, area-uniform) under the given feature settings, and
counts per relation: pairs the evidence gets right, the misses where it found no dominant
direction (and the ratio it saw), and the misses where it found one at the wrong angle.

Usage:
    .venv/bin/python bench/dominant_evidence.py --workspace train-workspace [--split val]
        [--input truth] [--pairs 600] [--set neighbours=12 flat=0.05 ...]

Nothing is asserted: it prints the counts.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import fields, replace
from pathlib import Path

import numpy as np

from cadio.capture.pair_features import FeatureConfig, dominant_direction, part_cloud
from models.relation_data import read_split

PARALLEL, PERPENDICULAR, COINCIDENT = 6, 7, 9  # label columns
ANGLE_DEG, RATIO = 3.0, 1.5  # geometric's angle test; the truth's dominance ratio
ANGLE_BANDS = (3.0, 10.0, 30.0, 60.0, 80.0, 87.0, 90.01)
RATIO_BANDS = (0.0, 1.2, 1.4, RATIO)


def evidence(points: np.ndarray, mm: np.ndarray, keys: list[tuple[str, ...]],
             cfg: FeatureConfig) -> np.ndarray:
    """(N, 3): found, angle between the two dominant directions (degrees), the smaller ratio;
    each part's cloud fitted once per key."""
    cache: dict[tuple[str, ...], tuple[np.ndarray | None, float]] = {}
    out = np.zeros((len(points), 3))
    for r in range(len(points)):
        doms = []
        for k in range(2):
            key = keys[2 * r + k]
            if key not in cache:
                cache[key] = dominant_direction(part_cloud(points[r, k] * mm[r], cfg), cfg)
            doms.append(cache[key])
        (da, ra), (db, rb) = doms
        if da is None or db is None:
            out[r] = (0.0, 90.0, 0.0)
        else:
            out[r] = (1.0, math.degrees(math.acos(min(1.0, abs(float(da @ db))))), min(ra, rb))
    return out


def report(name: str, e: np.ndarray, labels: np.ndarray) -> None:
    dominant = (e[:, 0] > 0) & (e[:, 2] >= RATIO)
    said = {PARALLEL: dominant & (e[:, 1] <= ANGLE_DEG) & ~labels[:, COINCIDENT],
            PERPENDICULAR: dominant & (e[:, 1] >= 90.0 - ANGLE_DEG)}
    for col, relation in ((PARALLEL, "parallel"), (PERPENDICULAR, "perpendicular")):
        truth, pred = labels[:, col], said[col]
        miss = truth & ~pred
        print(f"  {relation}: {truth.sum()} true of {len(truth)}; "
              f"right {np.mean(pred == truth):.3f}; false {np.sum(pred & ~truth)}; "
              f"missed {miss.sum()}: no dominant direction "
              f"{np.sum(miss & ~dominant)} (ratio seen in {list(RATIO_BANDS)}: "
              f"{np.histogram(e[miss & ~dominant, 2], RATIO_BANDS)[0].tolist()}), at another "
              f"angle {np.sum(miss & dominant)} (in {list(ANGLE_BANDS)}: "
              f"{np.histogram(e[miss & dominant, 1], ANGLE_BANDS)[0].tolist()})")
    print(f"  ({name}: a dominant direction on both parts in {dominant.mean():.3f} of the pairs)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workspace", type=Path, required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--input", default="truth", choices=["truth", "partial", "completed"])
    ap.add_argument("--pairs", type=int, default=600, help="clear pairs read (the first ones)")
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="FeatureConfig fields to change, each run beside the defaults")
    args = ap.parse_args()
    split = read_split(args.workspace / "datasets" / "relations" / f"{args.split}.npz")
    rows = np.flatnonzero(~split.meta["near_boundary"].to_numpy())[:args.pairs]
    meta = split.meta.iloc[rows]
    keys = [(str(s), str(v), str(p)) for s, v, a, b in zip(
        meta["scene"], meta["view"], meta["part_a"], meta["part_b"], strict=True)
        for p in (a, b)]
    points, labels = split.inputs[args.input][rows], split.labels[rows]
    mm = 1.0 / meta["scale_m_per_mm"].to_numpy()
    types = {f.name: type(f.default) for f in fields(FeatureConfig)}
    configs = [("defaults", FeatureConfig())]
    for item in args.set:
        field, value = item.split("=", 1)
        configs.append((item, replace(FeatureConfig(), **{field: types[field](value)})))
    print(f"{args.split}/{args.input}: {len(rows)} clear pairs")
    for name, cfg in configs:
        clock = time.perf_counter()
        e = evidence(points, mm, keys, cfg)
        print(f"{name} ({time.perf_counter() - clock:.0f} s)")
        report(name, e, labels)


if __name__ == "__main__":
    main()
