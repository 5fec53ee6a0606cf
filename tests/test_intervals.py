"""Intervals that resample what a figure rests on: source files for the completion headline
(each with all its parts), distinct pairs for the relation accuracy (each with all its views
and relations)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from reports.intervals import accuracy_interval, shape_mean_interval
from reports.relations import RELATIONS


def test_a_shape_mean_interval_resamples_files_and_holds_the_figure() -> None:
    rng = np.random.default_rng(1)
    values = rng.uniform(0.2, 0.8, 40)
    shapes, files = np.arange(40) // 2, np.arange(40) // 4  # two parts a shape, ten files
    low, high, n = shape_mean_interval(values, shapes, files)
    figure = pd.Series(values).groupby(shapes).mean().mean()
    assert n == 10 and low < figure < high and high - low < 0.4
    assert (low, high, n) == shape_mean_interval(values, shapes, files)  # seeded
    assert shape_mean_interval(values, shapes, files, seed=1) != (low, high, n)


def test_a_repeated_shape_weighs_once_in_every_draw() -> None:
    """A file of 28 identical balls scoring 0 beside two files of one part scoring 1: the
    mean per shape is 2/3 whichever files a draw holds both shapes of."""
    values = [0.0] * 28 + [1.0, 1.0]
    shapes = ["ball"] * 28 + ["pin", "pin"]
    files = ["bearing"] * 28 + ["pin-a", "pin-b"]
    low, high, n = shape_mean_interval(values, shapes, files)
    assert n == 3 and low == 0.0 and high == 1.0  # draws without the bearing, or only it
    mid, _, _ = shape_mean_interval(values, shapes, files, level=0.0)
    assert mid == pytest.approx(0.5)  # the median draw holds both shapes: (0 + 1) / 2


def test_one_file_gives_a_point_and_no_part_gives_nothing() -> None:
    assert shape_mean_interval([0.3, 0.5], ["a", "b"], ["f", "f"]) == (
        pytest.approx(0.4), pytest.approx(0.4), 1)
    low, high, n = shape_mean_interval([math.nan], ["a"], ["f"])
    assert math.isnan(low) and math.isnan(high) and n == 0


def test_the_accuracy_interval_resamples_pairs_with_all_their_relations() -> None:
    rows = []
    for pair in range(20):
        for view in range(3):
            for relation in RELATIONS:
                rows.append({"scene": "s", "part_a": f"a{pair}", "part_b": f"b{pair}",
                             "view": view, "relation": relation, "truth": True,
                             "predicted": pair >= 5})  # five pairs always wrong
    low, high, pairs = accuracy_interval(pd.DataFrame(rows))
    assert pairs == 20 and low < 0.75 < high
    swapped = pd.DataFrame(rows).rename(columns={"part_a": "part_b", "part_b": "part_a"})
    assert accuracy_interval(swapped) == (low, high, pairs)  # (a, b) and (b, a): one pair
    assert math.isnan(accuracy_interval(pd.DataFrame(rows).iloc[:0])[0])
