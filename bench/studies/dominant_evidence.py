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

With ``--parts N`` it reads parts instead, at the density the pair evidence is measured on
(``PairConfig.evidence_points`` CAD surface samples of the workspace's mesh, in the part's own
frame, with the exact normals of their faces as the ``truth`` evidence takes them, and with
local PCA's beside them): for N parts drawn from ``features/`` (seeded), whether the
evidence's dominant direction is the B-rep's (within 3 degrees, both at least 1.5 times the
runner-up), at another angle, missed, claimed where the B-rep has none, or rightly absent.
Any workspace with meshes and features will do (a night's, for parts no network trained on).

Usage:
    .venv/bin/python bench/studies/dominant_evidence.py --workspace train-workspace [--split val]
        [--input truth] [--pairs 600] [--set neighbours=12 flat=0.05 ...]
    .venv/bin/python bench/studies/dominant_evidence.py --workspace train-workspace --parts 600
        [--set neighbours=12,flat=0.05]

Nothing is asserted: it prints the counts.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import fields, replace
from pathlib import Path

import numpy as np

from cadio.evidence.cad_samples import placed_cad_samples
from cadio.evidence.pair_features import FeatureConfig, dominant_direction, part_cloud
from cadio.evidence.pairs import DEFAULT_PAIRS
from cadio.records import Features
from cadio.workspace import read_mesh
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


def part_agreement(workspace: Path, n: int, cfg: FeatureConfig, exact: bool = True
                   ) -> dict[str, int]:
    """Counts of N drawn parts: the evidence's dominant direction against the B-rep's, on the
    CAD samples with their faces' exact normals (as the ``truth`` input's evidence), or with
    local PCA's (``exact`` False)."""
    ids = sorted(p.stem for p in (workspace / "features").glob("*.json"))
    rng = np.random.default_rng(0)
    ids = [ids[i] for i in sorted(rng.choice(len(ids), min(n, len(ids)), replace=False))]
    counts = dict.fromkeys(("agree", "other_angle", "missed", "claimed", "rightly_none"), 0)
    for pid in ids:
        brep = json.loads((workspace / "features" / f"{pid}.json").read_text())
        direction, runner_up = brep.get("dominant_plane"), brep.get("dominant_runner_up")
        truth = direction is not None and runner_up is not None and runner_up <= 1 / RATIO
        samples = placed_cad_samples(read_mesh(workspace / "meshes" / f"{pid}.ply"),
                                     Features.from_dict(brep), pid, np.eye(4),
                                     DEFAULT_PAIRS.evidence_points, 1.0)
        cloud = part_cloud(samples[:, :3], cfg, samples[:, 3:] if exact else None)
        found, ratio = dominant_direction(cloud, cfg)
        seen = found is not None and ratio >= RATIO
        if truth and seen:
            angle = math.degrees(math.acos(min(1.0, abs(float(np.dot(found, direction))))))
            counts["agree" if angle <= ANGLE_DEG else "other_angle"] += 1
        else:
            counts["missed" if truth else "claimed" if seen else "rightly_none"] += 1
    return counts


def _value(kind: type, text: str) -> object:
    return text.lower() in ("1", "true", "yes") if kind is bool else kind(text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workspace", type=Path, required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--input", default="truth", choices=["truth", "partial", "completed"])
    ap.add_argument("--pairs", type=int, default=600, help="clear pairs read (the first ones)")
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="FeatureConfig fields to change, each item run beside the defaults")
    ap.add_argument("--parts", type=int, default=0,
                    help="read this many parts at the evidence's density instead of pairs")
    args = ap.parse_args()
    types = {f.name: type(f.default) for f in fields(FeatureConfig)}
    configs = [("defaults", FeatureConfig())]
    for item in args.set:  # one config per item; FIELD=VALUE,FIELD=VALUE changes several
        changes = dict(change.split("=", 1) for change in item.split(","))
        configs.append((item, replace(FeatureConfig(), **{
            field: _value(types[field], value) for field, value in changes.items()})))
    if args.parts:
        print(f"{args.parts} parts of {args.workspace} at {DEFAULT_PAIRS.evidence_points} "
              "CAD samples each")
        for name, cfg in configs:
            for exact in (True, False):
                counts = part_agreement(args.workspace, args.parts, cfg, exact)
                right = (counts["agree"] + counts["rightly_none"]) / max(sum(counts.values()), 1)
                normals = "exact normals" if exact else "PCA normals"
                print(f"{name}, {normals}: {counts}; right {right:.3f}")
        return
    split = read_split(args.workspace / "datasets" / "relations" / f"{args.split}.npz")
    rows = np.flatnonzero(~split.meta["near_boundary"].to_numpy())[:args.pairs]
    meta = split.meta.iloc[rows]
    keys = [(str(s), str(v), str(p)) for s, v, a, b in zip(
        meta["scene"], meta["view"], meta["part_a"], meta["part_b"], strict=True)
        for p in (a, b)]
    points, labels = split.inputs[args.input][rows], split.labels[rows]
    mm = 1.0 / meta["scale_m_per_mm"].to_numpy()
    print(f"{args.split}/{args.input}: {len(rows)} clear pairs")
    for name, cfg in configs:
        clock = time.perf_counter()
        e = evidence(points, mm, keys, cfg)
        print(f"{name} ({time.perf_counter() - clock:.0f} s)")
        report(name, e, labels)


if __name__ == "__main__":
    main()
