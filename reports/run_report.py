"""The report of one night, from the files its stages wrote into ``runs/<run_id>/``.

``write_run_report`` adds ``parts.parquet`` (one row per part, method, protocol and views:
the completion scores with the part's source file and status, its distinct shape and whether
the row scores it where it was placed), ``pairs.parquet`` (every
relation decision), ``categories.csv`` (each metric per category against its threshold, the
previous run and the last runs), ``junit.xml`` (one test case per category and metric),
``report.md`` (the checks in Markdown) and ``report.html`` (everything, self-contained: the
verdict of ``reports.verdict`` first, then every table folded). A run that completes writes
``summary.json`` last, after these (the report links it).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from cadio.workspace import atomic_path, atomic_write
from reports.asbuilt import junit_suites
from reports.completion import HELD_OUT, category_means, read_completion_parts
from reports.headline import HEADLINE_FILE, part_shapes, placed, read_headline
from reports.html import (
    Page,
    as_built_screen,
    assemblies_section,
    completion_section,
    first_screen,
    inspection_section,
    relations_section,
    trends_section,
)
from reports.shapes import read_part_geometry
from reports.tables import markdown_table, markdown_text
from reports.trends import (
    Thresholds,
    check_metrics,
    failed_checks,
    run_metrics,
    write_categories,
    write_junit,
)
from reports.verdict import (
    FLOORS_FILE,
    Verdict,
    assembly_intervals,
    build_verdict,
    completion_said,
    floors_said,
    read_problems,
)

SUMMARY = "summary.json"  # written last by a run that completed


@dataclass(frozen=True)
class RunReport:
    """What ``write_run_report`` wrote, and the checks that failed or regressed."""

    run_dir: str
    html: str
    markdown_path: str
    categories: str
    junit: str
    parts: str
    pairs: str
    failed: tuple[str, ...]
    markdown: str
    checks: tuple[dict[str, Any], ...]
    verdict: str = ""  # PASS, FAIL, or UNCHECKED where no check applied (reports.verdict)

    @property
    def passed(self) -> bool:
        return not self.failed

    def table_rows(self) -> list[dict[str, Any]]:
        """The checks as plain rows (for a table artifact): NaN as None."""
        return [{k: (None if isinstance(v, float) and v != v else v) for k, v in row.items()}
                for row in self.checks]


def previous_runs(runs_root: Path, run_id: str, n: int) -> list[Path]:
    """The last ``n`` runs before ``run_id`` that completed (they have a ``summary.json``),
    oldest first."""
    runs = sorted(p for p in Path(runs_root).iterdir()
                  if p.is_dir() and not p.is_symlink() and p.name < run_id
                  and (p / SUMMARY).is_file()) if Path(runs_root).is_dir() else []
    return runs[-n:] if n > 0 else []


def write_run_report(run_dir: Path, history: Sequence[Path], thresholds: Thresholds,
                     catalog: Path | None = None, facts: dict[str, Any] | None = None
                     ) -> RunReport:
    """Every report file of a run (see the module docstring).

    Args:
        run_dir: the run folder, holding what the stages wrote.
        history: earlier run folders, oldest first (``previous_runs``).
        thresholds: the per-category limits (``reports.trends.read_thresholds``).
        catalog: the workspace catalog, for each part's source file and status.
        facts: extra lines for the report's header (library, stage seconds, ...).

    Returns:
        The paths written and the failed checks.
    """
    run_dir = Path(run_dir)
    _keep_thresholds(run_dir, thresholds)
    earlier = [(p.name, run_metrics(p)) for p in history]
    current = run_metrics(run_dir)
    checks = check_metrics(current, [t for _, t in earlier], thresholds)
    write_categories(run_dir / "categories.csv", checks)
    as_built = _read_parquet(run_dir / "as_built.parquet")
    write_junit(run_dir / "junit.xml", checks, suite=f"nightly {run_dir.name}",
                more=junit_suites(as_built) if not as_built.empty else ())
    parts = _parts(run_dir, catalog)
    pairs = _read_parquet(run_dir / "relations_pairs.parquet")
    for name, frame in (("parts.parquet", parts), ("pairs.parquet", pairs)):
        with atomic_path(run_dir / name) as tmp:
            frame.to_parquet(tmp, index=False)
    failed = failed_checks(checks)
    markdown = _markdown(run_dir.name, checks, failed)
    with atomic_write(run_dir / "report.md", "w") as fh:
        fh.write(markdown)
    verdict = build_verdict(run_dir.name, checks, read_problems(run_dir))
    page = _page(run_dir, verdict, checks, parts, pairs, facts or {},
                 [*earlier, (run_dir.name, current)])
    with atomic_write(run_dir / "report.html", "w") as fh:
        fh.write(page)
    return RunReport(str(run_dir), str(run_dir / "report.html"), str(run_dir / "report.md"),
                     str(run_dir / "categories.csv"), str(run_dir / "junit.xml"),
                     str(run_dir / "parts.parquet"), str(run_dir / "pairs.parquet"),
                     tuple(failed), markdown, tuple(checks.to_dict("records")), verdict.word)


def _keep_thresholds(run_dir: Path, thresholds: Thresholds) -> None:
    """A copy of the thresholds file the run is checked against (``verdict.FLOORS_FILE``):
    the report says where its floors came from, and the run can be checked again."""
    source = Path(thresholds.source) if thresholds.source else None
    if source is not None and source.is_file():
        with atomic_write(run_dir / FLOORS_FILE, "wb") as fh:
            fh.write(source.read_bytes())


def _read_parquet(path: Path) -> pd.DataFrame:
    return pd.read_parquet(path) if path.is_file() else pd.DataFrame()


def _read_csv(path: Path) -> pd.DataFrame:
    return pd.read_csv(path) if path.is_file() and path.stat().st_size else pd.DataFrame()


def _parts(run_dir: Path, catalog: Path | None) -> pd.DataFrame:
    """Completion scores with each part's source file, name and ingest status, its distinct
    shape and whether the row scores it where it was placed (``reports.headline``)."""
    parts = read_completion_parts(run_dir) if (run_dir / "completion_parts.parquet").is_file() \
        else pd.DataFrame(columns=["part_id"])
    if catalog is None or not Path(catalog).is_file():
        return parts
    cols = ["part_id", "source", "name", "status", "error"]
    table = pd.read_parquet(catalog)
    table = table[[c for c in cols if c in table.columns]].drop_duplicates("part_id")
    parts = parts.merge(table, on="part_id", how="left")
    if parts.empty or "context" not in parts:
        return parts
    geometry = read_part_geometry(Path(catalog))
    return parts.assign(shape=part_shapes(parts["part_id"], geometry),
                        placed=placed(parts, geometry.set_index("part_id")["n_solids"]))


def _page(run_dir: Path, verdict: Verdict, checks: pd.DataFrame, parts: pd.DataFrame,
          pairs: pd.DataFrame, facts: dict[str, Any],
          history: Sequence[tuple[str, pd.DataFrame]]) -> str:
    """The verdict first, then every table folded, each with links to its files."""
    page = Page(f"mateqa nightly {run_dir.name}")
    problems = read_problems(run_dir)
    facts = {"run": run_dir.name, **facts, **_totals(run_dir)}
    categories = category_means(parts, HELD_OUT) if len(parts) else pd.DataFrame()
    observed = categories[categories["protocol"] == "observed"] if len(categories) else \
        categories
    mates = _read_csv(run_dir / "assembly_mates.csv")
    joints = _read_csv(run_dir / "assembly_joints.csv")
    first_screen(page, verdict, _facts_line(facts),
                 observed, mates, joints, assembly_intervals(run_dir),
                 [s for s in (completion_said(run_dir), floors_said(run_dir)) if s])
    as_built_screen(page, run_dir)

    def files(*names: str) -> list[str]:
        return [n for n in names if (run_dir / n).is_file()]

    with page.folded(f"Inputs that failed, and why ({len(problems)})",
                     files("ingest.md", "stages.md", "completion.md")):
        page.table(problems)
    with page.folded("The run: facts, totals and stage times",
                     [SUMMARY, *files("ingest.json", "stages.json", "tolerances.json")]):
        page.table(pd.DataFrame([{"item": k, "value": str(v)} for k, v in facts.items()]))
    with page.folded("Thresholds and the previous run", files("categories.csv", "junit.xml",
                                                             FLOORS_FILE)):
        page.table(checks, digits=4, status=True)
    with page.folded("Shape completion", files(HEADLINE_FILE, "completion_categories.csv",
                                               "completion_parts.parquet", "parts.parquet")):
        completion_section(page, parts, categories, read_headline(run_dir))
    with page.folded("Relations", files("relations_summary.csv", "relations_near_boundary.csv",
                                        "relations_pairs.parquet", "relations.md")):
        relations_section(page, _read_csv(run_dir / "relations_summary.csv"), pairs)
    with page.folded("Assemblies against their CAD mates",
                     files("assembly_mates.csv", "assembly_joints.csv")):
        assemblies_section(page, mates, joints)
    inspected = files("as_built.csv", "inspect_summary.csv", "inspect_poses.csv",
                      "inspect_defects.csv", "registered_mates.csv", "inspect.md")
    if inspected:  # a night that inspected nothing has no section of it
        with page.folded("As built: defects caught, false alarms, pose errors, registered "
                         "relations", inspected):
            inspection_section(page, run_dir)
    with page.folded("Trends over the last runs", files("categories.csv")):
        trends_section(page, history)
    return page.render()


def _facts_line(facts: dict[str, Any]) -> str:
    """The library, and the files and parts ingest found, in one line."""
    out = [f"library {facts['library']}"] if "library" in facts else []
    if "ingest files" in facts:
        out.append(f"{facts['ingest files']} files, {facts.get('ingest parts', 0)} parts")
    return " · ".join(out)


def _totals(run_dir: Path) -> dict[str, Any]:
    """The stage counts the ingest and stage reports wrote."""
    out: dict[str, Any] = {}
    for name in ("ingest.json", "stages.json"):
        path = run_dir / name
        if path.is_file():
            totals = json.loads(path.read_text()).get("totals", {})
            out.update({f"{name.split('.')[0]} {k}": v for k, v in totals.items()})
    return out


def _markdown(run_id: str, checks: pd.DataFrame, failed: list[str]) -> str:
    verdict = f"{len(failed)} checks failed" if failed else "every check passed"
    shown = checks[checks["status"] != "too-few"].copy()
    for col in ("value", "previous", "threshold", "mean_last_n"):
        shown[col] = shown[col].map(lambda v: "-" if v != v else f"{v:.4g}")
    lines = [f"# Nightly {markdown_text(run_id)}: {verdict}", "",
             *[f"- {markdown_text(f)}" for f in failed], "",
             markdown_table(shown[["category", "metric", "value", "previous", "threshold",
                                   "status", "mean_last_n", "n"]]), ""]
    return "\n".join(lines)
