"""Tests of reports.coverage: the parts of each category a night scored against those ingested."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from test_completion import BRAKES, MOTION, _row

from reports.completion import ALL, completion_markdown, parts_frame, write_completion
from reports.coverage import (
    COVERAGE_COLUMNS,
    COVERAGE_FILE,
    coverage_summary,
    part_coverage,
    read_part_coverage,
    write_part_coverage,
)


def _ingested(**categories: list[str]) -> pd.DataFrame:
    return pd.DataFrame([{"part_id": p, "category": c} for c, ids in categories.items()
                         for p in ids], columns=["part_id", "category"])


def test_coverage_counts_the_parts_scored_of_those_ingested_per_category() -> None:
    """A part counts once however many rows it has (train parts too: they are scored); a
    category nobody scored is 0 of its parts; a scored part ingest did not give is not
    counted; ``all`` is over every part."""
    parts = parts_frame([*(_row("a", view_deg=2.88 * k) for k in range(3)),
                         _row("a", method="carve"), _row("a", context="assembly"),
                         _row("b", split="train"), _row("stray", MOTION)])
    ingested = _ingested(**{BRAKES: ["a", "b", "c"], MOTION: ["m"], "other": ["o1", "o2"]})
    table = part_coverage(parts, ingested)
    assert tuple(table.columns) == COVERAGE_COLUMNS
    assert table["category"].tolist() == [*sorted([BRAKES, MOTION, "other"]), ALL]
    rows = table.set_index("category")
    assert rows.loc[BRAKES, ["parts_ingested", "parts_scored"]].tolist() == [3, 2]
    assert rows.loc[BRAKES, "coverage_parts"] == pytest.approx(2 / 3)
    assert rows.loc[MOTION, ["parts_ingested", "parts_scored", "coverage_parts"]].tolist() == [
        1, 0, 0.0]
    assert rows.loc[ALL, ["parts_ingested", "parts_scored"]].tolist() == [6, 2]
    assert coverage_summary(table)[BRAKES] == {"parts_ingested": 3, "parts_scored": 2,
                                               "coverage_parts": pytest.approx(2 / 3)}
    empty = part_coverage(parts_frame([]), _ingested())
    assert empty.set_index("category").loc[ALL, "parts_ingested"] == 0
    assert coverage_summary(empty)[ALL]["coverage_parts"] is None


def test_coverage_file_and_markdown_give_the_share_of_the_library(tmp_path: Path) -> None:
    parts = parts_frame([_row("a"), _row("b", split="train")])
    coverage = part_coverage(parts, _ingested(**{BRAKES: ["a", "b", "c", "d"]}))
    write_part_coverage(tmp_path, coverage)
    md = write_completion(tmp_path, parts, coverage)
    back = read_part_coverage(tmp_path)
    assert (tmp_path / COVERAGE_FILE).is_file() and tuple(back.columns) == COVERAGE_COLUMNS
    assert back.set_index("category").loc[BRAKES, "coverage_parts"] == 0.5
    text = md.read_text()
    assert "| category | parts_ingested | parts_scored | coverage_parts | train | test |" in text
    assert f"| {BRAKES} | 4 | 2 | 0.500 | 1 | 1 |" in text
    # a run written without the catalog (or before coverage) reads as no coverage
    assert read_part_coverage(tmp_path / "old").empty
    assert "parts_ingested" not in completion_markdown(parts)
    nothing = completion_markdown(parts_frame([]), library=part_coverage(
        parts_frame([]), _ingested(**{BRAKES: ["a"]})))
    assert "No completion scores" in nothing and f"| {BRAKES} | 1 | 0 | 0.000 |" in nothing
