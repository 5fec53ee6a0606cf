"""Benchmark of the one truth function (``cadio.truth.labels.label_placed``) on pair scenes.

Reads the single parts of a library (default: the built-in sample library, generated into a
temporary folder; ``--library DIR`` for a folder of STEP files such as ../shared/data/step),
describes each once (features, faces, axis lines), generates the scene table
(``--pairs`` per relation) and then labels every scene again on its own: pairs per second for
the generator (placement and labels) and for the labels alone, split by scenes whose parts
come within reach of each other (face mates measured) and those apart (no face work). It also
prints the label balance of the table: per relation, how many scenes hold it, and per intended
relation, the share that holds it (plain and near-boundary scenes apart).

Usage: ``PYTHONPATH=$PWD .venv/bin/python bench/speed/labels.py [--library DIR] [--pairs 100]``
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run from anywhere

from cadio.cad.ingest import STEP_SUFFIXES
from cadio.cad.step import read_step
from cadio.records import Relation
from cadio.truth.scenes import (
    SceneConfig,
    ScenePart,
    generate_scenes,
    label_pair,
    scene_part,
    scene_poses,
)

NAMES = [r.value for r in Relation]


def library_parts(root: Path) -> list[ScenePart]:
    """Every single-solid STEP file under ``root``, named by its path, in its folder's
    category."""
    parts = []
    for path in sorted(p for p in root.rglob("*") if p.suffix.lower() in STEP_SUFFIXES):
        solids = read_step(path)
        if len(solids) == 1:
            category = path.parent.name if path.parent != root else "parts"
            parts.append(scene_part(str(path.relative_to(root)), category, solids[0].shape))
    return parts


def measure(parts: list[ScenePart], pairs: int) -> tuple[pd.DataFrame, dict[str, float]]:
    cfg = SceneConfig(seed=0, pairs_per_relation=pairs)
    start = time.perf_counter()
    table = generate_scenes(parts, cfg)
    figures = {"scenes": len(table), "generate_s": time.perf_counter() - start}
    by_id = {p.part_id: p for p in parts}
    close = table["coincident_gap_mm"].notna() | table["concentric_gap_mm"].notna()
    for name, rows in (("close", table[close]), ("apart", table[~close])):
        start = time.perf_counter()
        for row in rows.to_dict("records"):
            label_pair(by_id[row["part_a"]], by_id[row["part_b"]], *scene_poses(row), cfg)
        figures[f"{name}_scenes"] = len(rows)
        figures[f"{name}_s"] = time.perf_counter() - start
    return table, figures


def balance(table: pd.DataFrame) -> pd.DataFrame:
    """Per relation: scenes where it holds, and the share of its intended scenes holding it."""
    plain, near = table[table["near_side"] == ""], table[table["near_side"] != ""]
    rows = []
    for name in NAMES:
        rows.append({
            "relation": name, "holds": int(table[name].sum()),
            "share": round(float(table[name].mean()), 3),
            "intended_plain": round(float(plain[plain["intended"] == name][name].mean()), 3),
            "intended_near_inside": round(float(
                near[(near["intended"] == name) & (near["near_side"] == "inside")][name].mean()),
                3),
            "near_boundary": int(table[table["intended"] == name]["near_boundary"].sum())})
    return pd.DataFrame(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--library", type=Path, help="folder of STEP files (default: samples)")
    parser.add_argument("--pairs", type=int, default=100, help="scenes per relation")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        root = args.library
        if root is None:
            from cadio.samples.library import generate_library

            root = Path(tmp)
            generate_library(root)
        start = time.perf_counter()
        parts = library_parts(root)
        describe_s = time.perf_counter() - start
    table, f = measure(parts, args.pairs)
    print(f"{len(parts)} single parts read and described in {describe_s:.1f} s")
    print(f"generator: {f['scenes']} scenes in {f['generate_s']:.1f} s "
          f"({f['scenes'] / f['generate_s']:.1f} scenes/s, placement and labels)")
    for name in ("close", "apart"):
        n, s = f[f"{name}_scenes"], f[f"{name}_s"]
        print(f"labels alone, parts {name}: {n} pairs in {s:.2f} s ({n / max(s, 1e-9):.1f} "
              "pairs/s)")
    n, s = f["close_scenes"] + f["apart_scenes"], f["close_s"] + f["apart_s"]
    print(f"labels alone, all: {n} pairs in {s:.2f} s ({n / s:.1f} pairs/s)")
    print(balance(table).to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
