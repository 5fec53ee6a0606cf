"""The ingest report: what was read per category, and every failure with its reason.

Pure pandas in, text out; the flow writes the files and publishes the same Markdown as a
Prefect artifact.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import pandas as pd


@dataclass(frozen=True)
class IngestReport:
    """Counts per category, the failures and skips, and totals."""

    per_category: pd.DataFrame
    problems: pd.DataFrame
    totals: dict[str, Any]
    warnings: pd.DataFrame

    def markdown(self) -> str:
        """The report as Markdown (tables of counts and problems)."""
        t = self.totals
        lines = [
            "# Ingest",
            "",
            f"{t['files']} files found: {t['ok']} ok, {t['failed']} failed, "
            f"{t['skipped']} skipped; {t['parts']} parts ({t['cached']} reused from cache); "
            f"worst tessellated-volume error {t['worst_volume_error_pct']:.3f}%.",
            "",
            "## Per category",
            "",
            markdown_table(self.per_category),
        ]
        if not self.problems.empty:
            lines += ["", "## Failed and skipped files", "", markdown_table(self.problems)]
        if not self.warnings.empty:
            lines += ["", "## Warnings", "", markdown_table(self.warnings)]
        return "\n".join(lines) + "\n"


def build_ingest_report(catalog: pd.DataFrame) -> IngestReport:
    """Summarise a catalog (see ``cadio.catalog``) into an ``IngestReport``."""
    files = _per_file(catalog)
    per_category = (
        files.groupby("category", sort=True)
        .agg(files=("source", "count"),
             ok=("file_status", lambda s: int((s == "ok").sum())),
             failed=("file_status", lambda s: int((s == "failed").sum())),
             skipped=("file_status", lambda s: int((s == "skipped").sum())),
             parts=("parts", "sum"),
             cached=("cached", "sum"))
        .reset_index()
    )
    bad = catalog[catalog["status"] != "ok"]
    problems = bad[["category", "source", "status", "error"]].reset_index(drop=True)
    ok = catalog[catalog["status"] == "ok"]
    worst = float(ok["volume_rel_error"].abs().max() * 100) if len(ok) else 0.0
    totals = {
        "files": len(files),
        "ok": int((files["file_status"] == "ok").sum()),
        "failed": int((files["file_status"] == "failed").sum()),
        "skipped": int((files["file_status"] == "skipped").sum()),
        "parts": len(ok),
        "cached": int(ok["cached"].sum()) if len(ok) else 0,
        "worst_volume_error_pct": worst if worst == worst else 0.0,
    }
    warned = catalog[(catalog["status"] == "ok") & (catalog["warning"].fillna("") != "")]
    warnings = warned[["category", "source", "name", "warning"]].reset_index(drop=True)
    return IngestReport(per_category, problems, totals, warnings)


def _per_file(catalog: pd.DataFrame) -> pd.DataFrame:
    """One row per source file: ok if any of its solids is ok."""
    if catalog.empty:
        return pd.DataFrame(columns=["category", "source", "file_status", "parts", "cached"])
    return (
        catalog.groupby(["category", "source"], sort=True)
        .agg(file_status=("status", lambda s: "ok" if (s == "ok").any() else str(s.iloc[0])),
             parts=("status", lambda s: int((s == "ok").sum())),
             cached=("cached", lambda s: int(s.sum())))
        .reset_index()
    )


def markdown_table(frame: pd.DataFrame) -> str:
    """A GitHub-flavoured Markdown table (no optional dependency on tabulate)."""
    cols = [str(c) for c in frame.columns]
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for row in frame.itertuples(index=False):
        out.append("| " + " | ".join(str(v).replace("|", "/") for v in row) + " |")
    return "\n".join(out)
