"""Benchmark and audit of the assembly variant families (``cadio.samples.assembly_variants``).

For N draws of each family: build and write the STEP file (wall and CPU seconds), read it back
(every part found under its name), check that no two parts share volume (``overlaps``), extract
the ground-truth mates (``cadio.truth.mates``) and count concentric and coincident face mates
and the promised mates the truth does not find. Draws run in isolated worker processes (two by
default). A variant is valid when it builds, reads back whole, has no interference and every
promised mate is found; distinct counts different descriptions (drawn parameters).

``--distinct N`` counts distinct descriptions among N draws of each family (no building).
``--write N`` also times ``write_assembly_variants`` on N variants with one and two workers,
and the rerun that finds every file up to date.

Usage: ``.venv/bin/python bench/speed/assembly_variants.py [--draws 4] [--families F ...]
[--workers 2] [--seed 0] [--write 0]``
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run from anywhere

import build123d as bd

from cadio.cad.step import read_step, write_step
from cadio.samples.assembly_variants import (
    FAMILIES,
    draw_assembly_variant,
    missing_mates,
    overlaps,
    write_assembly_variants,
)
from cadio.sandbox import Job, Limits, run_isolated
from cadio.truth.mates import read_assembly_mates


@dataclass(frozen=True)
class Audit:
    """One draw: what it is, what it cost (s), what the truth found."""

    family: str
    index: int
    description: str
    parts: int
    build_s: float
    write_s: float
    make_cpu_s: float
    read_ok: bool
    overlaps: int
    check_s: float
    check_cpu_s: float
    concentric: int
    concentric_fit: int
    coincident: int
    missing: int


@dataclass(frozen=True)
class _Draw:
    family: str
    index: int
    seed: int
    out_dir: str


def audit(draw: _Draw) -> Audit:
    """Build, write, read back and check one variant (the job of a worker process)."""
    v = draw_assembly_variant(draw.family, draw.index, draw.seed)
    wall, cpu = time.perf_counter(), time.process_time()
    solids = v.build()
    build_s = time.perf_counter() - wall
    path = Path(draw.out_dir) / f"{v.name}.step"
    write_step(bd.Compound(children=solids, label=v.name), path)
    write_s, make_cpu_s = time.perf_counter() - wall - build_s, time.process_time() - cpu
    wall, cpu = time.perf_counter(), time.process_time()
    read_ok = [s.info.name for s in read_step(path)] == list(v.parts)
    found = overlaps(solids)
    face = read_assembly_mates(path).level("face")
    check_s, check_cpu_s = time.perf_counter() - wall, time.process_time() - cpu
    concentric = face[face["relation"] == "concentric"]
    return Audit(v.family, v.index, v.description, len(solids), build_s, write_s, make_cpu_s,
                 read_ok, len(found), check_s, check_cpu_s, len(concentric),
                 int((concentric["fit"] == "fit").sum()),
                 int((face["relation"] == "coincident").sum()), len(missing_mates(v.mates, face)))


def print_table(audits: list[Audit], draws: int) -> None:
    by_family: dict[str, list[Audit]] = defaultdict(list)
    for a in audits:
        by_family[a.family].append(a)
    head = ("family", "draws", "built", "distinct", "read", "no-ovl", "mates", "valid", "parts",
            "make s", "make cpu", "check s", "check cpu", "conc", "fit", "coinc")
    print(f"{head[0]:16s}" + "".join(f"{h:>9s}" for h in head[1:9])
          + "".join(f"{h:>10s}" for h in head[9:13]) + "".join(f"{h:>7s}" for h in head[13:]))
    for family in FAMILIES:
        rows = by_family.get(family, [])
        if not rows:
            continue
        n = len(rows)
        valid = sum(a.read_ok and not a.overlaps and not a.missing for a in rows)

        def mean(values: list[float], count: int = n) -> float:
            return sum(values) / max(1, count)

        cells = (draws, n, len({a.description for a in rows}), sum(a.read_ok for a in rows),
                 sum(not a.overlaps for a in rows), sum(not a.missing for a in rows), valid,
                 mean([a.parts for a in rows]))
        times = (mean([a.build_s + a.write_s for a in rows]), mean([a.make_cpu_s for a in rows]),
                 mean([a.check_s for a in rows]), mean([a.check_cpu_s for a in rows]))
        counts = (mean([a.concentric for a in rows]), mean([a.concentric_fit for a in rows]),
                  mean([a.coincident for a in rows]))
        print(f"{family:16s}" + "".join(f"{c:>9.0f}" for c in cells[:7]) + f"{cells[7]:>9.1f}"
              + "".join(f"{t:>10.1f}" for t in times) + "".join(f"{c:>7.1f}" for c in counts))


def count_distinct(families: list[str], draws: int, seed: int) -> None:
    """Distinct drawn parameters (descriptions) among ``draws`` draws of each family."""
    for family in families:
        texts = {draw_assembly_variant(family, k, seed).description for k in range(draws)}
        print(f"{family:16s} {len(texts)} distinct of {draws} draws")


def time_writes(count: int, seed: int) -> None:
    for workers in (1, 2):
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            entries = write_assembly_variants(Path(tmp), count, seed, workers=workers)
            first = time.perf_counter() - start
            start = time.perf_counter()
            write_assembly_variants(Path(tmp), count, seed, workers=workers)
            again = time.perf_counter() - start
        print(f"write_assembly_variants({count}) with {workers} worker(s): {len(entries)} files, "
              f"{first:.1f} s ({first / max(1, len(entries)):.2f} s per variant), "
              f"rerun {again:.2f} s")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=4, help="draws per family")
    parser.add_argument("--families", nargs="*", default=list(FAMILIES))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--write", type=int, default=0, help="also time writing N variants")
    parser.add_argument("--distinct", type=int, default=0,
                        help="also count distinct descriptions among N draws per family")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    logging.getLogger("build123d").setLevel(logging.WARNING)
    audits, failed = [], []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        jobs = [Job(f"{f}-v{k:04d}", _Draw(f, k, args.seed, tmp))
                for k in range(args.draws) for f in args.families]
        for outcome in run_isolated(audit, jobs, Limits(seconds=900, workers=args.workers)):
            if outcome.result is not None:
                audits.append(outcome.result)
            else:
                failed.append(f"{outcome.job.key}: {outcome.error}")
    print(f"{len(audits)} of {len(jobs)} draws built in {time.perf_counter() - start:.0f} s "
          f"with {args.workers} workers; means per variant:")
    print_table(audits, args.draws)
    for line in failed:
        print("failed:", line)
    for a in sorted(audits, key=lambda a: (a.family, a.index)):
        if a.overlaps or a.missing or not a.read_ok:
            print(f"invalid {a.family}-v{a.index:04d} ({a.description}): read {a.read_ok}, "
                  f"{a.overlaps} overlapping pairs, {a.missing} promised mates missing")
    if args.distinct:
        count_distinct(args.families, args.distinct, args.seed)
    if args.write:
        time_writes(args.write, args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
