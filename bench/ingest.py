"""Benchmark: ingest of the real STEP files in ../shared/data/step.

Two measurements, printed as tables:
1. per stage, in this process: read (XDE), tessellate, features, voxelize at 64^3 — seconds,
   parts per second, and peak resident memory;
2. end to end through the crash-isolated worker pool (what ``mateqa ingest`` does), with 1 and
   with 2 workers: parts per second and peak memory of the supervisor and of its workers.

Usage: python bench/ingest.py [STEP_DIR] [--sizes 64]
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from cadio.cad.features import extract_features
from cadio.cad.ingest import IngestConfig, discover, ingest
from cadio.cad.step import read_step
from cadio.cad.tessellate import tessellate
from cadio.cad.voxels import voxelize
from cadio.sandbox import Limits

DEFAULT_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "step"


def _peak_mb(who: int = resource.RUSAGE_SELF) -> float:
    return resource.getrusage(who).ru_maxrss / 1024


def stages(root: Path, n: int) -> None:
    seconds: dict[str, float] = defaultdict(float)
    parts = 0
    for found in discover(root):
        t = time.perf_counter()
        solids = read_step(found.path)
        seconds["read"] += time.perf_counter() - t
        for solid in solids:
            t = time.perf_counter()
            mesh = tessellate(solid.shape)
            seconds["tessellate"] += time.perf_counter() - t
            t = time.perf_counter()
            extract_features(solid.shape)
            seconds["features"] += time.perf_counter() - t
            t = time.perf_counter()
            voxelize(mesh, n)
            seconds[f"voxels@{n}"] += time.perf_counter() - t
            parts += 1
    total = sum(seconds.values())
    print(f"\nPer stage, in process ({parts} parts, {len(discover(root))} files)")
    print(f"{'stage':<12} {'seconds':>9} {'ms/part':>9} {'parts/s':>9}")
    for name, s in [*seconds.items(), ("total", total)]:
        print(f"{name:<12} {s:>9.2f} {1000 * s / parts:>9.1f} {parts / s:>9.1f}")
    print(f"peak RSS of this process: {_peak_mb():.0f} MB")


def end_to_end(root: Path, n: int, workers: int) -> None:
    with tempfile.TemporaryDirectory() as ws:
        cfg = IngestConfig(voxel_sizes=(n,), limits=Limits(workers=workers))
        t = time.perf_counter()
        catalog = ingest(root, Path(ws), cfg)
        wall = time.perf_counter() - t
        t = time.perf_counter()
        again = ingest(root, Path(ws), cfg)
        rerun = time.perf_counter() - t
    ok = int((catalog["status"] == "ok").sum())
    print(f"{workers:>7} {len(catalog):>6} {ok:>5} {wall:>8.1f} {ok / wall:>8.2f} "
          f"{rerun:>8.2f} {int(again['cached'].sum()):>7} "
          f"{_peak_mb(resource.RUSAGE_CHILDREN):>10.0f}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", nargs="?", type=Path, default=DEFAULT_DIR)
    parser.add_argument("--size", type=int, default=64)
    args = parser.parse_args()
    if not args.root.is_dir():
        print(f"no STEP folder at {args.root}", file=sys.stderr)
        return 1
    stages(args.root, args.size)
    print("\nEnd to end through isolated workers (voxels at "
          f"{args.size}^3; rerun = unchanged files, from cache)")
    print(f"{'workers':>7} {'rows':>6} {'ok':>5} {'wall s':>8} {'parts/s':>8} "
          f"{'rerun s':>8} {'cached':>7} {'worker MB':>10}")
    for workers in (1, 2):
        end_to_end(args.root, args.size, workers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
