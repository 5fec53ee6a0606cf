"""The verdict of a night: per category pass or fail, the headline figures, the failed inputs.

A QA engineer reads this first, at the top of ``report.html`` and at the end of
``mateqa nightly``'s output. ``build_verdict`` makes it from the threshold checks
(``categories.csv``) and the inputs that failed (``ingest.json``, ``stages.json``);
``read_verdict`` reads both back from a run folder; ``console_verdict`` writes it as a dozen
lines of plain text; ``assembly_intervals`` says how far the assembly figures can be trusted.
Pure pandas, NumPy and the standard library: no CAD, no torch.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from reports.methods import completion_ours
from reports.tables import printable
from reports.trends import (
    ALL,
    CATEGORIES_COLUMNS,
    DEFAULT_THRESHOLDS,
    ThresholdsError,
    read_thresholds,
)

# The figures shown per category, then those the assemblies give (category "all" only).
# Completion: the mean per distinct shape over parts scored where they were placed
# (``reports.headline``), not the per-part mean over every context.
HEADLINE = ("completion_iou_shapes", "relation_accuracy", "ingest_ok_fraction", "mates_f1",
            "mates_f1_concentric", "mates_f1_coincident", "joint_agreement")
LABELS = {"completion_iou_shapes": "completion IoU per shape",
          "relation_accuracy": "relation accuracy", "ingest_ok_fraction": "ingest ok",
          "mates_f1": "mates F1 (mean of 10 relations)",
          "mates_f1_concentric": "concentric F1", "mates_f1_coincident": "coincident F1",
          "joint_agreement": "joint agreement"}
# A category's verdict is the first of these among its checks (all metrics, not only the
# headline): one failed check fails the category.
SEVERITY = ("fail", "regressed", "pass", "too-few", "no-threshold", "no-data")
FAILED = ("fail", "regressed")
PROBLEM_COLUMNS = ("stage", "item", "status", "reason")
SHOWN_FAILURES = 3  # failed checks listed on the console; the rest are in categories.csv


@dataclass(frozen=True)
class Figure:
    """One headline metric of a category: its value, threshold (floor), the previous night's
    value (NaN where none), status (``reports.trends.STATUSES``) and sample count."""

    metric: str
    value: float
    threshold: float
    previous: float
    status: str
    n: int


@dataclass(frozen=True)
class CategoryVerdict:
    """A category's verdict (the worst status of its checks), how many of its checks were
    applied and failed, and its headline figures."""

    category: str
    status: str
    checked: int
    failed: int
    figures: tuple[Figure, ...]

    def figure(self, metric: str) -> Figure | None:
        return next((f for f in self.figures if f.metric == metric), None)


@dataclass(frozen=True)
class Problem:
    """An input that failed or was skipped: the stage, the file or capture, why."""

    stage: str
    item: str
    status: str
    reason: str


@dataclass(frozen=True)
class Verdict:
    """The verdict of one night (see the module docstring)."""

    run_id: str
    categories: tuple[CategoryVerdict, ...]
    failed: tuple[str, ...]
    problems: tuple[Problem, ...]
    checked: int
    too_few: int
    has_previous: bool

    @property
    def passed(self) -> bool:
        """Some check applied and none failed: a night that checked nothing did not pass."""
        return not self.failed and self.checked > 0

    @property
    def word(self) -> str:
        """``PASS``, ``FAIL`` or ``UNCHECKED`` (no check applied: every value too few to check,
        without a threshold or without data)."""
        return "FAIL" if self.failed else "PASS" if self.checked else "UNCHECKED"

    def headline(self) -> str:
        """One sentence: pass, fail or unchecked, and how many checks applied."""
        checks = f"{self.checked} threshold check{'s' if self.checked != 1 else ''}"
        counts = (f"{len(self.failed)} of {checks} failed or regressed" if self.failed
                  else f"{'the' if self.checked == 1 else 'all'} {checks} passed")
        if not self.checked:
            counts = "no threshold check applied: this night checked nothing"
        few = f", {self.too_few} too few to check" if self.too_few else ""
        first = "" if self.has_previous else "; first night: no previous values"
        return f"Night {self.run_id}: {self.word}, {counts}{few}{first}"

    def problem_counts(self) -> str:
        """``3 (ingest 2, capture 1)``, or ``none``."""
        if not self.problems:
            return "none"
        counts = Counter(p.stage for p in self.problems)
        return f"{len(self.problems)} (" + ", ".join(f"{s} {n}" for s, n in counts.items()) + ")"


def build_verdict(run_id: str, checks: pd.DataFrame, problems: pd.DataFrame) -> Verdict:
    """The verdict of the checks of ``reports.trends.check_metrics`` and the problem table of
    ``read_problems``."""
    categories = sorted(set(checks["category"]), key=lambda c: (c == ALL, c))
    applied = checks["status"].isin(["pass", *FAILED])
    return Verdict(
        run_id=run_id,
        categories=tuple(_category(c, checks[checks["category"] == c]) for c in categories),
        failed=tuple(_failure(r) for r in checks[checks["status"].isin(FAILED)].itertuples()),
        problems=tuple(Problem(*(str(r[c]) for c in PROBLEM_COLUMNS))
                       for r in problems.to_dict("records")),
        checked=int(applied.sum()), too_few=int((checks["status"] == "too-few").sum()),
        has_previous=bool(checks["previous"].notna().any()))


def _category(category: str, rows: pd.DataFrame) -> CategoryVerdict:
    figures = tuple(
        Figure(str(r.metric), float(r.value), float(r.threshold), float(r.previous),
               str(r.status), int(r.n))
        for metric in HEADLINE for r in rows[rows["metric"] == metric].itertuples())
    statuses = rows["status"]
    return CategoryVerdict(category, worst(list(statuses)),
                           int(statuses.isin(["pass", *FAILED]).sum()),
                           int(statuses.isin(FAILED).sum()), figures)


def _failure(row: Any) -> str:
    """``fasteners completion_iou fail: 0.301 (floor 0.35)``, or for a regression the previous
    value and the allowed drop."""
    if row.status == "fail":
        side = "floor" if row.direction == "higher" else "ceiling"
        why = f"{side} {row.threshold:.3g}"
    else:
        why = f"previous {row.previous:.3g}, allowed drop {row.max_drop:.3g}"
    return f"{row.category} {row.metric} {row.status}: {row.value:.3g} ({why})"


def worst(statuses: Sequence[str]) -> str:
    """The worst of ``statuses`` in ``SEVERITY`` order (``no-data`` for none)."""
    return next((s for s in SEVERITY if s in statuses), "no-data")


def read_problems(run_dir: Path) -> pd.DataFrame:
    """Every input of the run that failed or was skipped, and why: the files ingest could not
    read (``ingest.json``) and the assemblies and captures that failed (``stages.json``)."""
    rows = []
    ingest, stages = Path(run_dir) / "ingest.json", Path(run_dir) / "stages.json"
    if ingest.is_file():
        rows += [{"stage": "ingest", "item": str(p.get("source", "")),
                  "status": str(p.get("status", "")), "reason": str(p.get("error", ""))}
                 for p in json.loads(ingest.read_text()).get("problems", [])]
    if stages.is_file():
        rows += [{"stage": str(p.get("stage", "")), "item": str(p.get("item", "")),
                  "status": "failed", "reason": str(p.get("error", ""))}
                 for p in json.loads(stages.read_text()).get("failures", [])]
    return pd.DataFrame(rows, columns=list(PROBLEM_COLUMNS))


def read_verdict(run_dir: Path) -> Verdict:
    """The verdict of a run folder whose report was written (``categories.csv``)."""
    run_dir = Path(run_dir)
    path = run_dir / "categories.csv"
    checks = pd.read_csv(path) if path.stat().st_size else pd.DataFrame()
    if checks.empty:
        checks = pd.DataFrame(columns=list(CATEGORIES_COLUMNS))
    return build_verdict(run_dir.name, checks, read_problems(run_dir))


def assembly_intervals(run_dir: Path) -> str:
    """The 95% intervals of the assemblies' mates F1 and joint agreement, each resampling the
    distinct pairs it rests on (``reports.intervals``), as one sentence; empty where the run
    scored no assembly. A figure over a few dozen pairs moves by tenths from night to night
    without anything changing: this says by how much."""
    from reports.intervals import joint_interval, mates_f1_interval
    from reports.methods import product

    run_dir = Path(run_dir)
    said = []
    pairs_path, joints_path = run_dir / "relations_pairs.parquet", run_dir / "assembly_joints.csv"
    if pairs_path.is_file():
        pairs = pd.read_parquet(pairs_path, columns=["scene", "part_a", "part_b", "input",
                                                     "method", "relation", "truth", "predicted"])
        given, method = product()
        mine = pairs[(pairs["input"] == given) & (pairs["method"] == method)
                     & pairs["scene"].astype(str).str.startswith("assembly-")]
        low, high, n = mates_f1_interval(mine)
        if n:
            said.append(f"mates F1 {low:.3f} to {high:.3f} ({n} pairs)")
    if joints_path.is_file() and joints_path.stat().st_size:
        joints = pd.read_csv(joints_path)
        if len(joints):
            low, high, n = joint_interval(joints)
            said.append(f"joint agreement {low:.3f} to {high:.3f} ({n} pairs)")
    return ("95% intervals over the distinct pairs: " + ", ".join(said)) if said else ""


def completion_said(run_dir: Path) -> str:
    """The completion headline of all categories with its interval and what it rests on, as
    one sentence (empty where the run has no headline file): the verdict's cell has room for
    the value only."""
    from reports.headline import read_headline

    table = read_headline(Path(run_dir))
    method, protocol = completion_ours()
    rows = table[(table["category"] == ALL) & (table["method"] == method)
                 & (table["protocol"] == protocol)]
    if rows.empty:
        return ""
    r = rows.iloc[0]
    interval = (f", 95% interval {r['iou_low']:.3f} to {r['iou_high']:.3f} over its "
                f"{int(r['n_files'])} files" if r["iou_low"] == r["iou_low"] else "")
    return (f"Completion IoU per shape {r['iou']:.3f}{interval}: {int(r['n_shapes'])} distinct "
            f"shapes of {int(r['n_parts'])} parts scored where they were placed (the per-part "
            f"mean over every context, parts re-rendered alone too: "
            f"{r['iou_all_contexts']:.3f} over {int(r['n_parts_all'])} parts)")


FLOORS_FILE = "thresholds.toml"  # the thresholds a run was checked against, as written


def floors_said(run_dir: Path) -> str:
    """Where the floors of a run came from, in one sentence (empty where the run kept no
    thresholds file): calibrated from a reference run, the shipped defaults, or set by hand."""
    path = Path(run_dir) / FLOORS_FILE
    if not path.is_file():
        return ""
    try:
        limits = read_thresholds(path)
    except ThresholdsError:
        return ""
    if limits.reference_run:
        return (f"Floors: calibrated from the run {printable(Path(limits.reference_run).name)} "
                f"({printable(limits.reference_run)}); see {FLOORS_FILE} in this run's folder")
    if path.read_bytes() == DEFAULT_THRESHOLDS.read_bytes():
        return ("Floors: the shipped defaults, loose enough for any library (a damaged model "
                "can pass them); `mateqa thresholds calibrate` sets floors from a healthy night")
    return f"Floors: set by hand; see {FLOORS_FILE} in this run's folder"


# ---------------------------------------------------------------- the console


def console_verdict(run_dir: Path) -> str:
    """The verdict of a run folder as about a dozen lines of text: the headline, one line per
    category with its figures, the failed checks, the failed inputs and where the report is."""
    run_dir = Path(run_dir).resolve()
    verdict = read_verdict(run_dir)
    said = [line for line in (completion_said(run_dir), floors_said(run_dir)) if line]
    lines = [verdict.headline(), *_figure_lines(verdict, assembly_intervals(run_dir)),
             *(f"  {line}" for line in said)]
    for line in verdict.failed[:SHOWN_FAILURES]:
        lines.append(f"  failed: {printable(line)}")
    if len(verdict.failed) > SHOWN_FAILURES:
        lines.append(f"  ... and {len(verdict.failed) - SHOWN_FAILURES} more failed checks in "
                     f"{run_dir / 'categories.csv'}")
    where = " (files and reasons: report.html, ingest.md, stages.md)" if verdict.problems else ""
    lines += [f"Failed inputs: {verdict.problem_counts()}{where}",
              f"Report: {run_dir / 'report.html'}",
              f"Full summary: {run_dir / 'summary.json'} (mateqa nightly --json prints it)"]
    return "\n".join(lines)


def _figure_lines(verdict: Verdict, intervals: str = "") -> list[str]:
    """The per-category table (completion, relations, ingest) and the assemblies' line. Pair
    categories (``a+b``) are listed only where they failed, and counted on a line of their own:
    a library of ten categories has 45 of them."""
    if not verdict.categories:
        return ["  no metrics in this run"]
    columns = HEADLINE[:3]
    pairs = pair_categories([c.category for c in verdict.categories])
    shown = [c for c in verdict.categories if c.category not in pairs or c.status in FAILED]
    rows = [["category", "verdict", *(LABELS[m] for m in columns)]]
    rows += [[printable(c.category), c.status, *(_cell(c.figure(m)) for m in columns)]
             for c in shown]
    widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]))]
    lines = ["  " + "  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)).rstrip()
             for r in rows]
    whole = next((c for c in verdict.categories if c.category == ALL), None)
    assembled = [f"{LABELS[m]} {_cell(whole.figure(m))}" for m in HEADLINE[3:]
                 if whole is not None and whole.figure(m) is not None]
    if assembled:
        lines.append("  assemblies against the CAD: " + ", ".join(assembled))
        if intervals:
            lines.append(f"    {intervals}")
    hidden = [c.status for c in verdict.categories if c.category in pairs
              and c.status not in FAILED]
    if hidden:
        counts = ", ".join(f"{n} {s}" for s, n in sorted(Counter(hidden).items(),
                                                          key=lambda i: SEVERITY.index(i[0])))
        lines.append(f"  {len(hidden)} pair categories (a+b) not shown: {counts}; "
                     "every one is in report.html")
    return lines


def pair_categories(categories: Sequence[str]) -> set[str]:
    """The categories of pairs of two others (``a+b`` where ``a`` and ``b`` are both among
    ``categories``): the relation figures of parts of two categories scored together."""
    names = set(categories)
    return {c for c in names if c.count("+") == 1 and all(p in names for p in c.split("+"))}


def _cell(figure: Figure | None) -> str:
    """``0.412``, with the status where it is not a plain pass (``0.301 fail``)."""
    if figure is None:
        return "-"
    value = "-" if math.isnan(figure.value) else f"{figure.value:.3f}"
    if figure.status in ("pass", "no-threshold"):
        return value
    if figure.status == "too-few":
        return f"{value} (n={figure.n}, too few)"
    return f"{value} {figure.status}"
