"""Benchmark of the as-built inspection: seconds per part of each of its phases on an assembly.

For each assembly of a workspace (one a night ingested, its mates written): the model (CAD
surfaces and symmetries), one intact capture by the night's inspection camera, and on it the
product's check (the design route on every view, then on one view alone), the search route
(every segment registered without the design), and the scoring beside them; wall seconds per
phase and per part, against the floor of 1 s per part for the product's check on two cores.
A ``mateqa nightly`` logs the whole stage's seconds (``inspection``) beside the others'.

Usage: ``.venv/bin/python bench/speed/inspection.py WORKSPACE [ASSEMBLY ...] [--views 4]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run from anywhere

import numpy as np
import pandas as pd

from cadio.inspect.defects import DefectPlan, Variant
from cadio.inspect.routes import by_design, by_search
from cadio.inspect.scan import scan_of
from cadio.inspect.stage import InspectConfig, assembly_model, capture_variant
from cadio.recordings.mcap_io import read_capture
from cadio.workspace import Workspace

FLOOR_S_PER_PART = 1.0


def measure(ws: Workspace, assembly: str, cfg: InspectConfig) -> dict[str, float | int | str]:
    """One assembly's phases, wall seconds."""
    seconds: dict[str, float] = {}
    clock = time.perf_counter()
    model = assembly_model(assembly, ws)
    seconds["model"] = time.perf_counter() - clock
    clock = time.perf_counter()
    path = capture_variant(model, Variant(assembly, "bench"), ws, cfg)
    seconds["capture"] = time.perf_counter() - clock
    clock = time.perf_counter()
    scan = scan_of(list(read_capture(path)))
    seconds["scan"] = time.perf_counter() - clock
    clock = time.perf_counter()
    by_design(model, scan, cfg.route, np.eye(4))
    seconds["check all views"] = time.perf_counter() - clock
    clock = time.perf_counter()
    by_design(model, scan.of_views([0]), cfg.route, np.eye(4))
    seconds["check one view"] = time.perf_counter() - clock
    clock = time.perf_counter()
    found = by_search(model, scan, cfg.route)
    seconds["search all views"] = time.perf_counter() - clock
    n = len(model.parts)
    return {"assembly": assembly, "parts": n, "segments": len(scan.segments),
            "found": len(found), **seconds,
            "check s/part": (seconds["scan"] + seconds["check all views"]) / n,
            "search s/part": seconds["search all views"] / n}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path, help="a workspace a night ingested")
    parser.add_argument("assemblies", nargs="*", help="assembly names (default: every one)")
    parser.add_argument("--views", type=int, default=4, help="inspection views (default 4)")
    args = parser.parse_args()
    ws = Workspace(args.workspace)
    names = args.assemblies or sorted(p.stem for p in (ws.root / "mates").glob("*.parquet"))
    cfg = InspectConfig(views=args.views, defects=DefectPlan(shifts_mm=(), turns_deg=(),
                                                             missing=False))
    rows = [measure(ws, name, cfg) for name in names]
    table = pd.DataFrame(rows)
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(table.round(2).to_string(index=False))
    total = table["parts"].sum()
    check = (table["check s/part"] * table["parts"]).sum() / total
    print(f"product's check: {check:.2f} s per part over {total} parts "
          f"(floor {FLOOR_S_PER_PART:.1f} s); search: "
          f"{(table['search s/part'] * table['parts']).sum() / total:.2f} s per part")


if __name__ == "__main__":
    main()
