"""``mateqa thresholds calibrate``: a thresholds file whose floors come from a healthy night.

The shipped floors suit any library and so catch little; a team's own night, checked against
floors set from an earlier healthy night of the same library (``reports.calibrate``), fails
when a figure falls by more than its sampling spread. No Prefect: it reads a run folder.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from flows.cli_options import bounded


def add_thresholds_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    """The ``thresholds`` command's parser."""
    p: argparse.ArgumentParser = sub.add_parser(
        "thresholds", help="calibrate per-category floors from a healthy night",
        description="Write a thresholds file (TOML, for nightly --thresholds) "
                       "whose floors come from a completed run: per category and figure, the "
                       "lower end of the figure's 95% interval in that run (files resampled "
                       "for the completion headline, distinct pairs for relations and mates). "
                       "A figure over fewer than --min-n parts, pairs or files gets no floor; "
                       "the file says why, and names the run.")
    p.add_argument("action", choices=["calibrate"], help="what to do")
    p.add_argument("--run", type=Path, required=True, metavar="RUN",
                   help="a completed run folder, e.g. WS/runs/latest or WS/runs/<run_id>")
    p.add_argument("--out", dest="thresholds_out", type=Path, required=True, metavar="FILE",
                   help="the thresholds file to write (TOML)")
    p.add_argument("--base", type=Path, default=None, metavar="FILE",
                   help="thresholds whose other limits (allowed drops, the ingest floor) the "
                   "file keeps (default: the shipped reports/thresholds.toml)")
    p.add_argument("--min-n", type=bounded(int, 0, 1_000_000), default=None,
                   help="figures over fewer parts, pairs or files get no floor (default: the "
                   "base file's min_n)")
    p.set_defaults(func=cmd_thresholds, tol=[], tolerances_file=None)
    return p


def cmd_thresholds(args: argparse.Namespace) -> int:
    from reports.calibrate import calibrate, write_calibration
    from reports.trends import DEFAULT_THRESHOLDS, ThresholdsError, read_thresholds

    run = args.run.resolve()
    problem = _not_a_run(run)
    if problem:
        print(f"mateqa thresholds: {problem}", file=sys.stderr)
        return 2
    try:
        base = read_thresholds(args.base or DEFAULT_THRESHOLDS)
    except ThresholdsError as exc:
        print(f"mateqa thresholds: --base {exc}", file=sys.stderr)
        return 2
    cal = calibrate(run, base, args.min_n)
    path = write_calibration(args.thresholds_out, cal)
    for f in cal.floors:
        said = f"floor {f.floor:.4f}: {f.reason}" if f.floor is not None else \
            f"no floor: {f.reason}"
        print(f"  {f.category!r} {f.metric}: {said}")
    print(f"wrote {path}, floors from the run {run.name}; check a night against them with "
          f"`mateqa nightly --thresholds {path}`")
    return 0


def _not_a_run(run: Path) -> str:
    """Why ``run`` is no completed run folder ("" when it is one)."""
    if not run.is_dir():
        return f"--run: {run} is not a folder"
    if not (run / "summary.json").is_file() or not (run / "categories.csv").is_file():
        return (f"--run: {run} is no completed run (no summary.json or categories.csv): "
                "calibrate from a night that finished")
    return ""
