"""The run's report files: what each stage did per category, and every failure with its reason.

``build_ingest_report`` and ``build_stage_report`` are pure (tables in, typed reports out);
``write_ingest_report`` and ``write_stage_report`` write them into ``runs/<run_id>/`` as
Markdown and JSON. The flow publishes the same Markdown as Prefect artifacts.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from cadio.contracts import CaptureSummary, MatesSummary
from cadio.workspace import atomic_write, write_json
from reports.tables import (
    captures_table,
    files_table,
    ingest_table,
    joints_table,
    markdown_table,
    mates_table,
    scenes_table,
)


@dataclass(frozen=True)
class IngestTotals:
    """Files found and their fate, parts read, parts reused, the worst volume error (%)."""

    files: int
    ok: int
    failed: int
    skipped: int
    parts: int
    cached: int
    worst_volume_error_pct: float


@dataclass(frozen=True)
class IngestReport:
    """Counts per category, the failures and skips, warnings and totals."""

    per_category: pd.DataFrame
    problems: pd.DataFrame
    warnings: pd.DataFrame
    totals: IngestTotals

    def markdown(self) -> str:
        """The report as Markdown (tables of counts and problems)."""
        t = self.totals
        lines = [
            "# Ingest", "",
            f"{t.files} files found: {t.ok} ok, {t.failed} failed, {t.skipped} skipped; "
            f"{t.parts} parts ({t.cached} reused from cache); worst tessellated-volume error "
            f"{t.worst_volume_error_pct:.3f}%.",
            "", "## Per category", "", markdown_table(self.per_category),
        ]
        if not self.problems.empty:
            lines += ["", "## Failed and skipped files", "", markdown_table(self.problems)]
        if not self.warnings.empty:
            lines += ["", "## Warnings", "", markdown_table(self.warnings)]
        return "\n".join(lines) + "\n"


def build_ingest_report(catalog: pd.DataFrame) -> IngestReport:
    """Summarise a catalog (see ``cadio.catalog``) into an ``IngestReport``."""
    files = files_table(catalog)
    ok = catalog[catalog["status"] == "ok"]
    worst = float(ok["volume_rel_error"].abs().max() * 100) if len(ok) else 0.0
    totals = IngestTotals(
        files=len(files), ok=int((files["file_status"] == "ok").sum()),
        failed=int((files["file_status"] == "failed").sum()),
        skipped=int((files["file_status"] == "skipped").sum()), parts=len(ok),
        cached=int(ok["cached"].sum()) if len(ok) else 0,
        worst_volume_error_pct=worst if worst == worst else 0.0,
    )
    bad = catalog[catalog["status"] != "ok"]
    warned = ok[ok["warning"].fillna("") != ""]
    return IngestReport(
        per_category=ingest_table(files),
        problems=bad[["category", "source", "status", "error"]].reset_index(drop=True),
        warnings=warned[["category", "source", "name", "warning"]].reset_index(drop=True),
        totals=totals)


def write_ingest_report(run_dir: Path, report: IngestReport) -> Path:
    """``ingest.md`` and ``ingest.json`` in ``run_dir``; returns the Markdown path."""
    run_dir.mkdir(parents=True, exist_ok=True)
    with atomic_write(run_dir / "ingest.md", "w") as fh:
        fh.write(report.markdown())
    write_json(run_dir / "ingest.json", {
        "totals": asdict(report.totals),
        "per_category": report.per_category.to_dict("records"),
        "problems": report.problems.to_dict("records"),
    })
    return run_dir / "ingest.md"


@dataclass(frozen=True)
class StageTotals:
    """What the stages after ingest did, over the whole library."""

    assemblies: int
    assemblies_failed: int
    face_mates: int
    joints: int
    scenes: int
    captures: int
    captures_failed: int
    frames: int
    input_parts: int


@dataclass(frozen=True)
class StageReport:
    """Per-category tables of mates, joints, scenes and captures, failures, totals."""

    tables: dict[str, pd.DataFrame]
    failures: pd.DataFrame
    captures: list[CaptureSummary]
    totals: StageTotals

    def markdown(self) -> str:
        text = "\n".join(f"## {name.capitalize()}\n\n{markdown_table(t)}\n"
                         for name, t in self.tables.items())
        if not self.failures.empty:
            text += "\n## Failures\n\n" + markdown_table(self.failures) + "\n"
        return text


def build_stage_report(mates: Sequence[MatesSummary], scenes: pd.DataFrame | None,
                       captures: Sequence[CaptureSummary],
                       part_categories: Mapping[str, str] | None = None) -> StageReport:
    """The stage report of one run (``scenes`` None when no scene table was built;
    ``part_categories``, part id -> category, files the captures of no scene)."""
    scene_frame = scenes if scenes is not None else pd.DataFrame(
        columns=["scene_id", "split", "intended", "category_a", "category_b"])
    tables = {"mates": mates_table(mates), "joints": joints_table(mates),
              "scenes": scenes_table(scene_frame), "captures": captures_table(captures, scene_frame,
                                                                              part_categories)}
    failures = pd.DataFrame(
        [{"stage": "mates", "category": m.category, "item": m.source, "error": m.error}
         for m in mates if not m.ok]
        + [{"stage": "capture", "category": "", "item": c.path or c.scene_id, "error": c.error}
           for c in captures if c.error],
        columns=["stage", "category", "item", "error"])
    totals = StageTotals(
        assemblies=len(mates), assemblies_failed=sum(not m.ok for m in mates),
        face_mates=sum(m.face_mates for m in mates), joints=sum(m.joints for m in mates),
        scenes=len(scene_frame), captures=len(captures),
        captures_failed=sum(bool(c.error) for c in captures),
        frames=sum(c.frames for c in captures), input_parts=sum(c.input_parts for c in captures))
    return StageReport(tables, failures, list(captures), totals)


def write_stage_report(run_dir: Path, report: StageReport) -> Path:
    """``stages.md`` and ``stages.json`` in ``run_dir``; returns the Markdown path."""
    run_dir.mkdir(parents=True, exist_ok=True)
    with atomic_write(run_dir / "stages.md", "w") as fh:
        fh.write(report.markdown())
    data: dict[str, Any] = {k: t.to_dict("records") for k, t in report.tables.items()}
    data["failures"] = report.failures.to_dict("records")
    data["totals"] = asdict(report.totals)
    data["captures_detail"] = [c.to_dict() for c in report.captures]
    write_json(run_dir / "stages.json", data)
    return run_dir / "stages.md"
