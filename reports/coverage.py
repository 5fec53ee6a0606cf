"""How much of the library a night scored: per category, the parts scored against those ingested.

A QA team reads the completion tables as covering its library, so the report says how many of
each category's parts they hold: ``runs/<run_id>/completion_coverage.csv``, one row per
category and ``all`` (last), columns ``COVERAGE_COLUMNS``: ``parts_ingested`` (the catalog's
``ok`` parts), ``parts_scored`` (those with a row in ``completion_parts``, any split or context:
a part a checkpoint trained on is scored, though left out of the means) and their share
``coverage_parts``. The same figures head ``completion.md``'s tables and sit under
``coverage`` in the run's ``summary.json`` (``coverage_summary``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pandas as pd

from cadio.errors import InputFileError
from cadio.workspace import atomic_write
from reports.completion import ALL

COVERAGE_FILE = "completion_coverage.csv"
COVERAGE_COLUMNS = ("category", "parts_ingested", "parts_scored", "coverage_parts")


def part_coverage(parts: pd.DataFrame, ingested: pd.DataFrame) -> pd.DataFrame:
    """Per category (and ``all``, last): parts ingested, parts scored and the share scored.

    Args:
        parts: ``completion_parts`` rows (their ``part_id`` is what counts).
        ingested: the parts the library gave, columns ``part_id`` and ``category`` (the
            catalog's ``ok`` rows).

    Returns:
        Columns ``COVERAGE_COLUMNS``; ``coverage_parts`` is NaN for a category without parts.
        A scored part that ingest did not give (another library's) is not counted.
    """
    known = ingested[["part_id", "category"]].astype("str").drop_duplicates("part_id")
    scored = known[known["part_id"].isin(set(parts["part_id"].astype(str)))]
    order = [*sorted(set(known["category"])), ALL]
    counts = pd.DataFrame({
        "parts_ingested": _per_category(known).reindex(order, fill_value=0),
        "parts_scored": _per_category(scored).reindex(order, fill_value=0),
    }).astype("int64")
    counts["coverage_parts"] = (counts["parts_scored"] / counts["parts_ingested"].where(
        counts["parts_ingested"] > 0)).astype("float64")
    return counts.rename_axis("category").reset_index()[list(COVERAGE_COLUMNS)]


def _per_category(rows: pd.DataFrame) -> pd.Series:
    counts = rows.groupby("category").size()
    counts[ALL] = len(rows)
    return counts


def coverage_summary(coverage: pd.DataFrame) -> dict[str, dict[str, Any]]:
    """``part_coverage``'s table as category -> {parts_ingested, parts_scored,
    coverage_parts} (a run's ``summary.json``; NaN as None)."""
    return {str(r["category"]): {
        "parts_ingested": int(r["parts_ingested"]), "parts_scored": int(r["parts_scored"]),
        "coverage_parts": None if math.isnan(r["coverage_parts"]) else float(
            r["coverage_parts"])} for r in coverage.to_dict("records")}


def write_part_coverage(run_dir: Path, coverage: pd.DataFrame) -> Path:
    """``completion_coverage.csv`` in ``run_dir``, atomically (NaN as an empty field).

    Raises:
        ValueError: the table does not have the columns ``COVERAGE_COLUMNS``.
    """
    if tuple(coverage.columns) != COVERAGE_COLUMNS:
        raise ValueError(f"coverage must have the columns {COVERAGE_COLUMNS}")
    path = run_dir / COVERAGE_FILE
    with atomic_write(path, "w") as fh:
        coverage.to_csv(fh, index=False)
    return path


def read_part_coverage(run_dir: Path) -> pd.DataFrame:
    """``completion_coverage.csv`` of ``run_dir`` (empty, with its columns, when the run has
    none: one written before coverage was reported, or without a catalog).

    Raises:
        InputFileError: the file has other columns.
    """
    path = run_dir / COVERAGE_FILE
    if not path.is_file():
        return pd.DataFrame(columns=list(COVERAGE_COLUMNS))
    frame = pd.read_csv(path, dtype={"category": "str"}, keep_default_na=False, na_values=[""])
    if tuple(frame.columns) != COVERAGE_COLUMNS:
        raise InputFileError(path, f"columns {tuple(frame.columns)}, not {COVERAGE_COLUMNS}")
    return frame.astype({"parts_ingested": "int64", "parts_scored": "int64",
                         "coverage_parts": "float64"})
