"""The completion headline: per distinct shape, over parts scored where they were placed, with
an interval over files; the IoU that counts the truth outside the grid as missed."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from cadio.errors import InputFileError
from reports.completion import METRICS, category_means, parts_frame
from reports.headline import (
    HEADLINE_COLUMNS,
    HEADLINE_FILE,
    headline_markdown,
    headline_table,
    iou_counting_outside,
    placed,
    read_headline,
    write_headline,
)
from reports.metrics import iou, missing
from reports.shapes import GEOMETRY_COLUMNS


def _row(part: str, context: str = "pair", iou: float = 0.5, **fields: Any) -> dict[str, Any]:
    row: dict[str, Any] = {"part_id": part, "category": "c", "split": "test", "context": context,
                           "method": "gan_lstm", "protocol": "observed", "n_views": 1,
                           "view_deg": 0.0, **dict.fromkeys(METRICS, 0.0), "coverage": 1.0}
    return {**row, "iou": iou, **fields}


def _geometry(parts: dict[str, tuple[str, float, int]]) -> pd.DataFrame:
    """part -> (file, volume, solids in its file); the volume is the shape (area follows)."""
    return pd.DataFrame([{"part_id": p, "source": f, "category": "c", "volume": v, "area": v,
                          "n_faces": 6, "n_solids": n} for p, (f, v, n) in parts.items()],
                        columns=list(GEOMETRY_COLUMNS))


# A rack of ten identical teeth inside its assembly, a tooth and a gear the assembly hid
# (re-rendered alone), and two single-part files: one in a pair scene, one alone.
GEOMETRY = _geometry({**{f"tooth{k}": ("rack.step", 1.0, 13) for k in range(10)},
                      "hidden-tooth": ("rack.step", 1.0, 13), "gear": ("rack.step", 9.0, 13),
                      "bolt": ("bolt.step", 2.0, 1), "nut": ("nut.step", 3.0, 1)})
ROWS = [*(_row(f"tooth{k}", "assembly", 0.2) for k in range(10)),
        _row("hidden-tooth", "alone", 0.9), _row("gear", "alone", 0.95),
        _row("bolt", "pair", 0.5), _row("nut", "alone", 0.8)]


def _all(table: pd.DataFrame, method: str = "gan_lstm") -> pd.Series:
    return table.set_index(["category", "method", "protocol"]).loc[("all", method, "observed")]


def test_a_part_counts_where_it_was_placed_and_each_shape_once() -> None:
    parts = parts_frame(ROWS)
    assert placed(parts, GEOMETRY.set_index("part_id")["n_solids"]).tolist() == [
        *[True] * 10, False, False, True, True]  # alone counts for a single-part file only
    row = _all(headline_table(parts, GEOMETRY))
    assert (row["n_parts"], row["n_shapes"], row["n_files"]) == (12, 3, 3)
    assert row["iou"] == pytest.approx((0.2 + 0.5 + 0.8) / 3)  # tooth, bolt, nut once each
    assert row["iou_parts"] == pytest.approx((10 * 0.2 + 0.5 + 0.8) / 12)
    assert (row["n_rerendered"], row["iou_rerendered"]) == (2, pytest.approx(0.925))
    per_part = category_means(parts).set_index(["category", "method"]).loc[("all", "gan_lstm")]
    assert (row["n_parts_all"], row["iou_all_contexts"]) == (14, pytest.approx(per_part["iou"]))
    assert row["iou_low"] <= row["iou"] <= row["iou_high"]


def test_without_repeats_or_re_renders_the_headline_is_the_per_part_mean() -> None:
    rows = [_row(f"p{k}", iou=k / 10) for k in range(8)]
    geometry = _geometry({f"p{k}": (f"f{k}.step", 1.0 + k, 1) for k in range(8)})
    row = _all(headline_table(parts_frame(rows), geometry))
    assert row["iou"] == pytest.approx(row["iou_all_contexts"]) == pytest.approx(0.35)
    assert row["iou"] == pytest.approx(row["iou_parts"])
    assert row["iou_outside"] == pytest.approx(row["iou"])  # every part wholly in its grid


def test_the_interval_resamples_files_and_is_seeded() -> None:
    rows = [_row(f"p{k}", iou=k / 20) for k in range(20)]
    geometry = _geometry({f"p{k}": (f"f{k // 2}.step", 1.0 + k, 1) for k in range(20)})
    first, again = (headline_table(parts_frame(rows), geometry) for _ in range(2))
    assert first.equals(again)
    row = _all(first)
    assert row["n_files"] == 10 and row["iou_low"] < row["iou"] < row["iou_high"]
    one_file = _all(headline_table(parts_frame(rows), geometry.assign(source="one.step")))
    assert one_file["iou_low"] == one_file["iou_high"] == pytest.approx(one_file["iou"])


def test_counting_the_truth_outside_the_grid_as_missed_is_the_iou_on_a_larger_grid() -> None:
    rng = np.random.default_rng(0)
    truth = np.zeros((24, 24, 24), bool)
    truth[4:20, 6:18, 2:22] = True  # reaches out of the grid [0:16]^3 the view placed
    pred = np.zeros_like(truth)
    pred[:16, :16, :16] = rng.random((16, 16, 16)) < 0.6
    inside = (slice(0, 16),) * 3
    counted = iou_counting_outside(iou(pred[inside], truth[inside]),
                                   missing(pred[inside], truth[inside]),
                                   truth[inside].sum() / truth.sum())
    assert counted == pytest.approx(iou(pred, truth))
    assert iou_counting_outside(0.7, 0.1, 1.0) == pytest.approx(0.7)  # all inside: unchanged
    assert iou_counting_outside([0.0, 0.5], [1.0, float("nan")], [0.5, 0.5]).tolist() == [0, 0]
    assert iou_counting_outside(0.7, 0.1, float("nan")) == pytest.approx(0.7)  # unknown


def test_the_headline_file_round_trips_and_the_markdown_names_what_it_counts(
        tmp_path: Path) -> None:
    table = headline_table(parts_frame([*ROWS, _row("bolt", method="r2n2")]), GEOMETRY)
    assert tuple(table.columns) == HEADLINE_COLUMNS and table["category"].iloc[-1] == "all"
    write_headline(tmp_path, table)
    back = read_headline(tmp_path)
    assert back.shape == table.shape and np.allclose(back["iou"], table["iou"])
    text = headline_markdown(table)
    assert "per distinct shape" in text and "r2n2 (surface only)" in text
    assert read_headline(tmp_path / "absent").empty
    (tmp_path / HEADLINE_FILE).write_text("category,iou\nall,0.5\n")
    with pytest.raises(InputFileError, match="columns"):
        read_headline(tmp_path)
    assert headline_table(parts_frame([]), GEOMETRY).empty
    assert math.isnan(_all(headline_table(parts_frame([_row("gear", "alone")]),
                                          GEOMETRY))["iou"])
