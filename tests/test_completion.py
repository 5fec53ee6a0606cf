"""Tests of reports.completion: the two report files, how means weigh parts and views, the
tables beside the paper, and the report section."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from cadio.errors import InputFileError
from cadio.records import Category
from reports.completion import (
    ALL,
    CATEGORY_COLUMNS,
    CONTEXTS_FILE,
    PARTS_FILE,
    PARTS_SCHEMA,
    CompletionCase,
    category_means,
    completion_markdown,
    context_iou_table,
    context_means,
    iou_by_n_views,
    iou_by_view_angle,
    paper_iou_table,
    paper_overlap_table,
    parts_frame,
    read_completion_categories,
    read_completion_parts,
    write_completion,
    write_completion_parts,
)
from reports.metrics import METRICS

BRAKES, MOTION = Category.BRAKES.value, Category.MOTION.value


def _row(part: str, category: str = BRAKES, **fields: Any) -> dict[str, Any]:
    """One scored prediction: a test-split single view of gan_lstm, observed, metrics 0.5."""
    row: dict[str, Any] = {"part_id": part, "category": category, "split": "test",
                           "context": "pair", "method": "gan_lstm", "protocol": "observed",
                           "n_views": 1, "view_deg": 0.0, **dict.fromkeys(METRICS, 0.5),
                           "coverage": 1.0}
    return {**row, **fields}


def _views(part: str, count: int, **fields: Any) -> list[dict[str, Any]]:
    return [_row(part, view_deg=2.88 * k, **fields) for k in range(count)]


def _means(rows: list[dict[str, Any]]) -> pd.DataFrame:
    return category_means(parts_frame(rows)).set_index(["category", "method", "protocol"])


def test_parts_file_round_trip_keeps_columns_dtypes_and_nan(tmp_path: Path) -> None:
    parts = parts_frame([_row("a"), _row("b", MOTION, chamfer_l1=np.nan, method="carve",
                                         protocol="oracle-box", n_views=4, view_deg=43.2)])
    path = write_completion_parts(tmp_path, parts)
    assert path == tmp_path / PARTS_FILE
    assert [p.name for p in tmp_path.iterdir()] == [PARTS_FILE]  # no temporary file left
    back = read_completion_parts(tmp_path)
    assert list(back.columns) == list(PARTS_SCHEMA)
    assert {c: str(t) for c, t in back.dtypes.items()} == PARTS_SCHEMA
    pd.testing.assert_frame_equal(back, parts)


def test_parts_frame_refuses_what_the_contract_forbids(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown protocols"):
        parts_frame([_row("a", protocol="oracle")])
    with pytest.raises(ValueError, match="scored twice"):
        parts_frame([_row("a"), _row("a")])
    parts_frame([_row("a").copy()]).drop(columns="fscore").to_parquet(tmp_path / PARTS_FILE)
    with pytest.raises(InputFileError, match="fscore"):
        read_completion_parts(tmp_path)


def test_a_scored_case_is_a_row_of_the_parts_file() -> None:
    truth = np.zeros((32, 32, 32), dtype=bool)
    truth[8:20, 8:24, 4:28] = True
    case = CompletionCase("p", BRAKES, "test", "visible", "observed", 1, 0.0)
    row = parts_frame([case.score(truth, truth, voxel_mm=0.5)]).iloc[0]
    assert row["iou"] == 1.0 and row["chamfer_l1"] == 0.0 and row["method"] == "visible"
    with pytest.raises(ValueError, match="unknown protocol"):
        CompletionCase("p", BRAKES, "test", "visible", "truth-box", 1, 0.0)


def test_a_part_with_eight_views_weighs_as_much_as_a_part_with_one() -> None:
    means = _means([*_views("many", 8, iou=1.0), _row("one", iou=0.0)])
    assert means.loc[(BRAKES, "gan_lstm", "observed"), "iou"] == pytest.approx(0.5)  # not 8/9
    assert means.loc[(BRAKES, "gan_lstm", "observed"), "n_parts"] == 2


def test_the_all_row_is_over_parts_and_only_held_out_single_views_count() -> None:
    rows = [_row("a", iou=0.9), _row("b", MOTION, iou=0.3), _row("c", MOTION, iou=0.6),
            _row("t", MOTION, iou=0.0, split="train"), _row("m", iou=0.0, n_views=2)]
    table = category_means(parts_frame(rows))
    assert list(table.columns) == list(CATEGORY_COLUMNS)
    assert table["category"].tolist() == [BRAKES, MOTION, ALL]
    everything = table.set_index("category").loc[ALL]
    assert everything["iou"] == pytest.approx(0.6)  # (0.9 + 0.3 + 0.6) / 3, not 0.675
    assert everything["n_parts"] == 3


def test_an_empty_prediction_counts_as_a_failure_without_making_means_nan() -> None:
    truth = np.zeros((32, 32, 32), dtype=bool)
    truth[8:20, 8:24, 4:28] = True
    good = np.roll(truth, 1, axis=0)
    rows = [CompletionCase(part, BRAKES, "test", "gan_lstm", "observed", 1, 0.0)
            .score(pred, truth, voxel_mm=0.5)
            for part, pred in (("good", good), ("empty", np.zeros_like(truth)))]
    parts = parts_frame(rows)
    scores = parts.set_index("part_id")
    means = _means(rows).loc[(BRAKES, "gan_lstm", "observed")]
    assert means["iou"] == pytest.approx(scores.loc["good", "iou"] / 2)  # the empty one is 0
    assert means["missing"] == pytest.approx((scores.loc["good", "missing"] + 1) / 2)
    # The empty one costs the part's diagonal in Chamfer distance: the mean cannot improve.
    assert means["chamfer_l1"] == pytest.approx((scores.loc["good", "chamfer_l1"]
                                                 + scores.loc["empty", "chamfer_l1"]) / 2)
    assert scores.loc["empty", "chamfer_l1"] > 10 * scores.loc["good", "chamfer_l1"]
    # Undefined for the empty prediction: left out, so the mean is the good part's own.
    assert means["composition_error"] == pytest.approx(scores.loc["good", "composition_error"])
    assert "1 prediction is empty" in completion_markdown(parts)


def test_categories_file_round_trip(tmp_path: Path) -> None:
    parts = parts_frame([*_views("a", 3), _row("b", MOTION, chamfer_l1=np.nan, method="ae")])
    md = write_completion(tmp_path, parts)
    assert md.read_text() == completion_markdown(parts)
    back = read_completion_categories(tmp_path)
    pd.testing.assert_frame_equal(back, category_means(parts))
    assert math.isnan(back.set_index(["category", "method"]).loc[(MOTION, "ae"), "chamfer_l1"])


def test_view_angle_bins_hold_25_of_the_125_views_each() -> None:
    # View k's IoU is its bin's index / 10 when bins are 72 degrees (25 views) wide.
    rows = [_row("a", view_deg=2.88 * k, iou=(k // 25) / 10) for k in range(125)]
    table = iou_by_view_angle(parts_frame(rows))
    bins = ["0-72", "72-144", "144-216", "216-288", "288-360"]
    assert list(table.columns) == ["protocol", "category", "method", *bins]
    row = table.set_index("category").loc[ALL]
    assert row[bins].tolist() == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4])


def test_iou_against_the_number_of_views_weighs_parts_equally() -> None:
    rows = [_row("a", n_views=n, iou=n / 10) for n in (1, 2, 4, 8)]
    rows += [_row("b", n_views=8, view_deg=2.88 * k, iou=0.0) for k in range(5)]
    table = iou_by_n_views(parts_frame(rows)).set_index("category")
    assert list(table.columns) == ["protocol", "method", "1", "2", "4", "8"]
    assert table.loc[ALL, "8"] == pytest.approx(0.4)  # (0.8 + 0.0) / 2 parts


def test_tables_beside_the_paper() -> None:
    rows = [_row("a", iou=0.7), _row("b", iou=0.5, method="r2n2"),
            _row("c", "other", overlap_xy=0.614, overlap_yz=0.2, overlap_zx=1.0)]
    categories = category_means(parts_frame(rows))
    iou_table = paper_iou_table(categories).set_index("category")
    surface = "r2n2 (surface only)"  # it reads the seen surface alone: labelled, not renamed
    assert list(iou_table.columns) == ["protocol", "n_parts", "gan_lstm", surface, "paper",
                                       "paper_r2n2"]
    assert iou_table.loc[BRAKES, ["gan_lstm", surface, "paper", "paper_r2n2"]].tolist() == (
        pytest.approx([70.0, 50.0, 70.48, 64.2]))
    assert set(categories["method"]) == {"gan_lstm", "r2n2"}  # the file keeps the name
    assert iou_table.loc[ALL, "paper"] == 57.23 and math.isnan(iou_table.loc["other", "paper"])
    overlap = paper_overlap_table(categories).set_index("category")
    assert overlap.loc[BRAKES, "paper"] == "60/47/86"
    assert overlap.loc["other", "gan_lstm"] == "61/20/100" and overlap.loc["other", "paper"] == (
        "-/-/-")


def test_report_section_states_split_sizes_and_the_protocol_of_every_table() -> None:
    rows = [_row("a"), _row("b", split="train"), _row("c", MOTION, split="val"),
            _row("a", protocol="oracle-box")]
    text = completion_markdown(parts_frame(rows))
    assert "| category | train | val | test |" in text
    assert f"| {BRAKES} | 1 | 0 | 1 |" in text and f"| {ALL} | 1 | 1 | 1 |" in text
    headings = [line for line in text.splitlines() if line.startswith("#### ")]
    assert len(headings) == 10
    assert all(h.endswith(("protocol: observed", "protocol: oracle-box")) for h in headings)
    assert "No prediction is empty." in text
    assert completion_markdown(parts_frame([])).endswith("No completion scores in this run.\n")


def test_parts_seen_in_pairs_and_inside_assemblies_are_reported_apart(tmp_path: Path) -> None:
    """A part seen in a pair scene and inside an assembly counts in each context; the coverage
    of its grids is averaged like a metric; old files without either still read."""
    rows = [_row("a", iou=0.8, coverage=1.0), _row("a", context="assembly", iou=0.2,
                                                     coverage=0.6),
            _row("b", context="assembly", iou=0.4, coverage=0.8)]
    parts = parts_frame(rows)
    table = context_means(parts).set_index(["category", "context", "method", "protocol"])
    assert table.loc[(ALL, "pair", "gan_lstm", "observed"), "iou"] == pytest.approx(0.8)
    assert table.loc[(ALL, "assembly", "gan_lstm", "observed"), "iou"] == pytest.approx(0.3)
    assert table.loc[(ALL, "assembly", "gan_lstm", "observed"), "coverage"] == pytest.approx(0.7)
    # part a: the mean of its two contexts (0.8), then over the parts
    assert _means(rows).loc[(ALL, "gan_lstm", "observed"), "coverage"] == pytest.approx(0.8)
    wide = context_iou_table(context_means(parts))
    assert set(wide["context"]) == {"pair", "assembly"} and "gan_lstm" in wide
    write_completion(tmp_path, parts)
    assert (tmp_path / CONTEXTS_FILE).exists()
    assert "inside assemblies" in (tmp_path / "completion.md").read_text()
    old = parts.drop(columns=["context", "coverage"])
    old.drop_duplicates(["part_id", "method"]).to_parquet(tmp_path / PARTS_FILE)
    assert set(read_completion_parts(tmp_path)["context"]) == {"pair"}
