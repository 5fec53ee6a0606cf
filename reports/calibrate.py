"""Floors calibrated from a reference night: each figure less the margin its own sampling
spread gives.

The shipped floors (``reports/thresholds.toml``) must suit any library, so they sit far below
what a healthy night measures (a completion floor of 0.10 under a figure of 0.5): a night with
a damaged model passes them. A QA team's library is the same every night, so its own healthy
night says what to expect: ``calibrate`` takes each figure of a reference run that has a 95%
interval (the completion headline's over files, the relation and assembly figures' over
distinct pairs: ``reports.intervals``), per category, and sets its floor at the interval's
lower end, the value less the spread that drawing other parts, files or pairs of the same kind
would give by chance. A figure over fewer than ``min_n`` parts, pairs or files gets no floor
(it would not be checked), nor does one whose interval rests on fewer than ``min_n`` files or
distinct pairs (the spread of a handful says little); the file says why for each.
Every other limit (the drops allowed against the previous night, the ingest floor) is kept
from the base thresholds. ``calibration_toml`` writes the thresholds file, naming the
reference run (``reference_run``), which ``reports.trends.read_thresholds`` reads back.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import pandas as pd

from cadio.workspace import atomic_write
from reports.headline import read_headline
from reports.intervals import (
    LEVEL,
    accuracy_interval,
    f1_interval,
    joint_interval,
    mates_f1_interval,
)
from reports.methods import completion_ours, product
from reports.tables import printable
from reports.trends import ALL, METRICS, Limit, Thresholds, run_metrics


@dataclass(frozen=True)
class Floor:
    """One figure of the reference run and the floor set from it (None, with ``reason``,
    where none is). low, high: its 95% interval; n: the count the check compares with
    ``min_n`` (unit: what it counts); drawn: the units the interval resampled (files or
    distinct pairs, ``drawn_unit``)."""

    category: str
    metric: str
    value: float
    low: float
    high: float
    n: int
    unit: str
    drawn: int
    drawn_unit: str
    floor: float | None
    reason: str


@dataclass(frozen=True)
class Calibration:
    """The floors of one reference run, over the limits of ``base``."""

    reference_run: str
    base: Thresholds
    min_n: int
    floors: tuple[Floor, ...]


SPREAD_COLUMNS = ["category", "low", "high", "drawn"]


def _completion_spread(run: Path) -> pd.DataFrame:
    table = read_headline(run)
    method, protocol = completion_ours()
    rows = table[(table["method"] == method) & (table["protocol"] == protocol)]
    return rows.rename(columns={"iou_low": "low", "iou_high": "high", "n_files": "drawn"})[
        SPREAD_COLUMNS]


_PAIR_COLUMNS = ["scene", "part_a", "part_b", "category", "input", "method", "relation",
                 "truth", "predicted", "near_boundary"]


def _pairs(run: Path, answers: tuple[str, str]) -> pd.DataFrame:
    """The relation rows of one input and method."""
    path = run / "relations_pairs.parquet"
    pairs = pd.read_parquet(path, columns=_PAIR_COLUMNS) if path.is_file() else pd.DataFrame(
        columns=_PAIR_COLUMNS)
    return pairs[(pairs["input"] == answers[0]) & (pairs["method"] == answers[1])]


def _spread(groups: list[tuple[str, pd.DataFrame]],
            interval: Callable[[pd.DataFrame], tuple[float, float, int]]) -> pd.DataFrame:
    return pd.DataFrame([(str(c), *interval(g)) for c, g in groups if len(g)],
                        columns=SPREAD_COLUMNS)


def _accuracy_spread(run: Path) -> pd.DataFrame:
    pairs = _pairs(run, product())
    clear = pairs[~pairs["near_boundary"].astype(bool)]
    return _spread([(ALL, clear), *clear.groupby("category", sort=True)], accuracy_interval)


def _assemblies(run: Path) -> pd.DataFrame:
    pairs = _pairs(run, product())
    return pairs[pairs["scene"].astype(str).str.startswith("assembly-")]


def _mates_spread(run: Path) -> pd.DataFrame:
    return _spread([(ALL, _assemblies(run))], mates_f1_interval)


def _mate_spread(relation: str) -> Callable[[Path], pd.DataFrame]:
    def read(run: Path) -> pd.DataFrame:
        rows = _assemblies(run)
        return _spread([(ALL, rows[rows["relation"] == relation])], f1_interval)
    return read


def _joint_spread(run: Path) -> pd.DataFrame:
    path = run / "assembly_joints.csv"
    joints = pd.read_csv(path) if path.is_file() and path.stat().st_size else pd.DataFrame()
    return _spread([(ALL, joints)], joint_interval)


# metric -> (what its check's n counts, what its interval resamples, reader of a run folder:
# SPREAD_COLUMNS)
SPREADS: dict[str, tuple[str, str, Callable[[Path], pd.DataFrame]]] = {
    "completion_iou_shapes": ("shapes", "files", _completion_spread),
    "relation_accuracy": ("pair views", "pairs", _accuracy_spread),
    "mates_f1": ("true pair views", "pairs", _mates_spread),
    "mates_f1_concentric": ("true pair views", "pairs", _mate_spread("concentric")),
    "mates_f1_coincident": ("true pair views", "pairs", _mate_spread("coincident")),
    "joint_agreement": ("jointed pair views", "pairs", _joint_spread),
}


def calibrate(run_dir: Path, base: Thresholds, min_n: int | None = None) -> Calibration:
    """The floors of the figures of ``SPREADS`` in a reference run.

    Args:
        run_dir: a completed run folder (its report written).
        base: the thresholds whose other limits the calibrated file keeps.
        min_n: a figure gets no floor where its check counts fewer parts, pairs or files, or
            where its interval resampled fewer files or distinct pairs (the spread of a
            handful is no guide) (default: base's).

    Returns:
        Every figure of the run that ``SPREADS`` names, with its floor or why it has none.
    """
    run_dir = Path(run_dir)
    needed = base.min_n if min_n is None else min_n
    figures = run_metrics(run_dir)
    floors = []
    for metric, (unit, drawn_unit, spread) in SPREADS.items():
        mine = figures[figures["metric"] == metric].merge(spread(run_dir), on="category",
                                                          how="left")
        for r in mine.itertuples():
            figure = Floor(str(r.category), metric, float(r.value), float(r.low),
                           float(r.high), int(r.n), unit, _count(float(r.drawn)), drawn_unit,
                           None, "")
            floors.append(_floor(figure, needed))
    return Calibration(str(run_dir.resolve()), base, needed, tuple(floors))


def _count(value: float) -> int:
    """A count that the merge may have left NaN (no interval for the figure): 0 then."""
    return 0 if math.isnan(value) else int(value)


def _floor(figure: Floor, min_n: int) -> Floor:
    """``figure`` with the interval's lower end as its floor, or None and the reason."""
    f = figure
    reason = ""
    if math.isnan(f.value):
        reason = "no value in the reference run"
    elif f.n < min_n:
        reason = f"{f.n} {f.unit}, fewer than min_n = {min_n}: not checked"
    elif f.drawn < min_n or math.isnan(f.low):
        reason = (f"its interval rests on {f.drawn} {f.drawn_unit}, fewer than min_n = "
                  f"{min_n}: the spread of so few is no guide")
    if reason:
        return replace(f, reason=reason)
    # rounded down, so that the reference run clears its own floors as written
    return replace(f, floor=math.floor(min(f.low, f.value) * 1e4) / 1e4,
                   reason=f"value {f.value:.4f}, {LEVEL:.0%} interval {f.low:.4f} to "
                   f"{f.high:.4f} over {f.drawn} {f.drawn_unit} ({f.n} {f.unit})")


def calibration_toml(cal: Calibration) -> str:
    """The thresholds file of a calibration (``reports/thresholds.toml``'s format, with
    ``reference_run``): the base limits of every metric, then per category the calibrated
    floors, each with the figure and interval it came from; the figures without a floor as
    comments saying why."""
    lines = [f"# Floors calibrated from the run {_quoted(cal.reference_run)}.",
             f"# Each is the lower end of the figure's {LEVEL:.0%} interval in that run (source "
             "files resampled for", "# completion, distinct pairs for relations and mates). "
             "Other limits are the base thresholds'",
             f"# ({_quoted(cal.base.source or 'defaults')}).", "",
             f"min_n = {cal.min_n}", f"reference_run = {_quoted(cal.reference_run)}"]
    for metric in METRICS:
        lines += _metric_lines(metric, cal)
    return "\n".join(lines) + "\n"


def _metric_lines(metric: str, cal: Calibration) -> list[str]:
    base = cal.base.limits.get(metric, Limit())
    mine = [f for f in cal.floors if f.metric == metric]
    over = cal.base.categories.get(metric, {})
    if base == Limit() and not mine and not over:
        return []
    lines = ["", f"[{metric}]", *_limit_lines(base),
             *(f"# {_quoted(f.category)}: no floor: {printable(f.reason)}" for f in mine
               if f.floor is None)]
    for category, limit in over.items():
        if not any(f.category == category and f.floor is not None for f in mine):
            lines += ["", f"[{metric}.categories.{_quoted(category)}]", *_limit_lines(limit)]
    for f in mine:
        if f.floor is None:
            continue
        kept = over.get(f.category, Limit())
        lines += ["", f"[{metric}.categories.{_quoted(f.category)}]",
                  f"floor = {f.floor:.4f}  # {printable(f.reason)}",
                  *_limit_lines(Limit(max_drop=kept.max_drop))]
    return lines


def _limit_lines(limit: Limit) -> list[str]:
    return [f"{key} = {value!r}" for key, value in (("floor", limit.floor),
                                                     ("max_drop", limit.max_drop))
            if value is not None]


def _quoted(text: str) -> str:
    """A TOML basic string (a JSON string with non-ASCII escaped is one): category names and
    paths may hold any character."""
    return json.dumps(text).replace("\x7f", "\\u007f")  # TOML, unlike JSON, escapes DEL


def write_calibration(path: Path, cal: Calibration) -> Path:
    """``calibration_toml`` written to ``path`` atomically."""
    with atomic_write(Path(path), "w") as fh:
        fh.write(calibration_toml(cal))
    return Path(path)
