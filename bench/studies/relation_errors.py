"""What the relation errors on real assemblies are made of: each assembly pair's CAD gap.

A night scores ``concentric`` and ``coincident`` against the CAD's face mates, which hold within
0.1 mm (coincident) and 1 mm (concentric). This reads a night's ``relations_pairs.parquet`` and,
for every pair of parts of an assembly scene, how far apart the two parts are in the CAD: the
nearest distance between their surfaces, sampled on the workspace's meshes (every vertex plus
6,000 evenly spread surface samples per part) and placed as the assembly places them, so it is
approximate to about the meshes' chordal deflection and sample spacing. Per input, method and
relation it counts true and false positives and false negatives by gap band, and the F1 with and
without the pairs whose gap lies between the mate's tolerance and 2 mm: parts that nearly touch,
which no input of a few millimetres' resolution (a completed 64^3 grid over a 200 mm assembly
has 3 mm voxels) can tell from parts that do.

Usage:
    .venv/bin/python bench/studies/relation_errors.py --workspace heldout/ws [--run RUN_DIR]
        [--relations concentric coincident] [--methods ltn geometric]

Nothing is asserted: it prints the tables.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
import trimesh
from scipy.spatial import cKDTree

from cadio.catalog import read_catalog
from reports.relations import scores

BANDS = (-np.inf, 0.1, 0.5, 1.0, 2.0, 5.0, np.inf)  # mm
NEAR_MISS_MM = 2.0  # gaps above the tolerance and up to this are near misses


class PlacedSurfaces:
    """Each part's surface samples in its assembly's frame, built once per part."""

    def __init__(self, workspace: Path) -> None:
        self.meshes = workspace / "meshes"
        self.catalog = read_catalog(workspace / "catalog.parquet").set_index("part_id")
        self.points: dict[str, np.ndarray] = {}
        self.trees: dict[str, cKDTree] = {}

    def of(self, part: str) -> np.ndarray:
        if part not in self.points:
            mesh = trimesh.load(self.meshes / f"{part}.ply", force="mesh")
            samples, _ = trimesh.sample.sample_surface_even(mesh, 6000, seed=0)
            pose = np.asarray(self.catalog.at[part, "placement"], float).reshape(4, 4)
            local = np.vstack([mesh.vertices, samples])
            self.points[part] = local @ pose[:3, :3].T + pose[:3, 3]
        return self.points[part]

    def gap_mm(self, a: str, b: str) -> float:
        if b not in self.trees:
            self.trees[b] = cKDTree(self.of(b))
        return float(self.trees[b].query(self.of(a))[0].min())


def f1(frame: pd.DataFrame) -> float:
    return scores(frame["truth"].to_numpy(), frame["predicted"].to_numpy())["f1"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, required=True)
    parser.add_argument("--run", type=Path, help="a run folder (default: the workspace's latest)")
    parser.add_argument("--relations", nargs="+", default=["concentric", "coincident"])
    parser.add_argument("--methods", nargs="+", default=["ltn", "geometric"])
    args = parser.parse_args()
    run = args.run or (args.workspace / "runs" / "latest").resolve()
    rows = pd.read_parquet(run / "relations_pairs.parquet")
    rows = rows[rows["scene"].str.startswith("assembly") & rows["relation"].isin(args.relations)
                & rows["method"].isin(args.methods)].copy()
    if rows.empty:
        raise SystemExit(f"{run}: no assembly pairs of {args.relations} by {args.methods}")
    surfaces = PlacedSurfaces(args.workspace)
    pairs = rows[["part_a", "part_b"]].drop_duplicates()
    gaps = {(a, b): surfaces.gap_mm(a, b) for a, b in pairs.itertuples(index=False)}
    rows["gap_mm"] = [gaps[(a, b)] for a, b in zip(rows["part_a"], rows["part_b"], strict=True)]
    rows["band"] = pd.cut(rows["gap_mm"], BANDS).astype(str)
    rows["outcome"] = np.select(
        [rows["truth"] & rows["predicted"], rows["predicted"], rows["truth"]],
        ["tp", "fp", "fn"], "tn")
    print(f"# {run.name}: {len(pairs)} assembly pairs, {rows['scene'].nunique()} views\n")
    table = rows.pivot_table(index=["input", "method", "relation", "band"], columns="outcome",
                             values="view", aggfunc="size", fill_value=0)
    print(table.to_string(), "\n")
    tolerance = {"coincident": 0.1, "concentric": 1.0}
    summary = []
    for (inp, method, relation), group in rows.groupby(["input", "method", "relation"]):
        near = group["gap_mm"].between(tolerance.get(relation, 0.1), NEAR_MISS_MM,
                                       inclusive="right") & ~group["truth"]
        summary.append({"input": inp, "method": method, "relation": relation, "f1": f1(group),
                        "near_miss_fp": int((near & group["predicted"]).sum()),
                        "f1_without_near_misses": f1(group[~near])})
    print(pd.DataFrame(summary).to_string(index=False, float_format=lambda v: f"{v:.3f}"))


if __name__ == "__main__":
    main()
