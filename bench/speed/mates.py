"""Benchmark of ground-truth mate extraction on the largest real assemblies.

For each assembly: all pairs of parts, pairs passing the enlarged-box filter, pairs in contact
(exact distance within ``contact_mm``), the rows produced per level, and seconds per phase
(read, features, prune = boxes + exact contact, face mates, relations, joints), printed as a
table. The default set (the three largest by solid count) runs in well under two minutes.

Usage: ``.venv/bin/python bench/speed/mates.py [STEP_FILE ...] [--all]``
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run from anywhere

from cadio.truth.mates import read_assembly_mates

ASSEMBLIES = Path(__file__).resolve().parents[2] / "shared" / "data" / "step" / "assemblies"
DEFAULT = ("kcl_pipe-flange-assembly.step", "occt_pm4_rotor-pump-assembly.stp",
           "occt_as1_motor.step")
PHASES = ("read", "features", "prune", "face_mates", "relations", "joints")


def measure(path: Path) -> dict[str, object]:
    """One assembly: pair counts, row counts per level and seconds per phase."""
    start = time.perf_counter()
    result = read_assembly_mates(path)
    total = time.perf_counter() - start
    levels = result.table["level"].value_counts()
    return {
        "assembly": path.name, "parts": result.n_parts, "pairs": result.n_pairs,
        "boxed": result.n_box_pairs, "contact": result.n_contact_pairs,
        "face": int(levels.get("face", 0)), "part": int(levels.get("part", 0)),
        "joint": int(levels.get("joint", 0)),
        **{p: result.seconds.get(p, 0.0) for p in PHASES}, "total": total,
    }


def print_table(rows: list[dict[str, object]]) -> None:
    """Fixed-width table: counts, then seconds per phase."""
    counts = ("parts", "pairs", "boxed", "contact", "face", "part", "joint")
    times = (*PHASES, "total")
    print(f"{'assembly':34s}" + "".join(f"{c:>8s}" for c in counts)
          + "".join(f"{t:>11s}" for t in times))
    for r in rows:
        print(f"{str(r['assembly'])[:34]:34s}" + "".join(f"{r[c]:>8d}" for c in counts)
              + "".join(f"{r[t]:>10.2f}s" for t in times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("files", nargs="*", type=Path, help="STEP assemblies (default: 3 largest)")
    parser.add_argument("--all", action="store_true", help="every file in the assemblies folder")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    files = list(args.files)
    if args.all:
        files = sorted(p for p in ASSEMBLIES.iterdir() if p.suffix.lower() in (".step", ".stp"))
    elif not files:
        files = [ASSEMBLIES / name for name in DEFAULT]
    missing = [f for f in files if not f.is_file()]
    if missing:
        sys.exit(f"not found: {', '.join(map(str, missing))}")
    print_table([measure(f) for f in files])


if __name__ == "__main__":
    main()
