"""The relation report's files: columns that other tools read, and scores that add up."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from reports.relations import (
    ASSEMBLY_COLUMNS,
    PAIR_COLUMNS,
    SUMMARY_COLUMNS,
    accuracy_table,
    joint_interval,
    pairs_frame,
    scores,
    write_relation_report,
)


def _rows(scene: str, method: str, truth: list[bool], predicted: list[bool],
          near: bool = False, category: str = "gears") -> list[dict[str, object]]:
    return [{"scene": scene, "view": i, "part_a": "a", "part_b": "b", "category": category,
             "input": "completed", "method": method, "relation": "left", "truth": t,
             "predicted": p, "confidence": 0.9, "near_boundary": near, "violation": i == 0}
            for i, (t, p) in enumerate(zip(truth, predicted, strict=True))]


def test_scores_count_hits_and_misses() -> None:
    s = scores(np.array([1, 1, 0, 0], bool), np.array([1, 0, 1, 0], bool))
    assert (s["n"], s["accuracy"], s["precision"], s["recall"], s["f1"]) == (4, 0.5, 0.5, 0.5,
                                                                              0.5)
    none = scores(np.zeros(3, bool), np.zeros(3, bool))
    assert none["accuracy"] == 1.0 and math.isnan(none["precision"]) and math.isnan(none["f1"])


def test_report_files_keep_their_columns_and_split_near_boundary_pairs(tmp_path: Path) -> None:
    rows = (_rows("s1", "ltn", [True, False, True], [True, False, False])
            + _rows("s2", "ltn", [True], [False], near=True)
            + _rows("assembly-stack", "ltn", [True, True], [True, True], category="asm"))
    md = write_relation_report(tmp_path, pairs_frame(rows), notes=["a note"])
    pairs = pd.read_parquet(tmp_path / "relations_pairs.parquet")
    assert tuple(pairs.columns[:len(PAIR_COLUMNS)]) == PAIR_COLUMNS and len(pairs) == 6
    summary = pd.read_csv(tmp_path / "relations_summary.csv")
    assert tuple(summary.columns) == SUMMARY_COLUMNS
    overall = summary[summary["category"] == "all"].iloc[0]
    assert overall["n"] == 5 and overall["accuracy"] == 4 / 5  # the near pair is left out
    assert overall["violation_rate"] == 2 / 5
    near = pd.read_csv(tmp_path / "relations_near_boundary.csv")
    assert near[near["category"] == "all"]["n"].tolist() == [1]
    asm = pd.read_csv(tmp_path / "assembly_mates.csv")
    assert tuple(asm.columns) == ASSEMBLY_COLUMNS
    left = asm[(asm["assembly"] == "assembly-stack") & (asm["relation"] == "left")].iloc[0]
    assert (left["n_cad"], left["n_pred"], left["f1"]) == (2, 2, 1.0)
    assert "Table III" in md.read_text() and "a note" in md.read_text()


def test_accuracy_table_sits_beside_the_paper() -> None:
    from reports.relations import summary_frame

    table = accuracy_table(summary_frame(pairs_frame(_rows("s", "mlp", [True, False],
                                                           [True, True]))))
    assert table.loc["left", "completed/mlp"] == 50.0
    assert table.loc["left", "paper"] == 99.7 and table.loc["left", "RANSEM"] == 86.8


def test_joint_types_follow_the_predicted_concentric_and_coincident() -> None:
    from cadio.truth.joints import predicted_joint
    from reports.relations import joint_frame

    assert [predicted_joint(c, k) for c, k in [(True, True), (True, False), (False, True),
                                               (False, False)]] == [
        "revolute", "cylindrical", "planar", "none"]
    rows = []
    for rel, pred in (("concentric", True), ("coincident", True), ("left", False)):
        for r in _rows("assembly-shaft", "ltn", [True], [pred]):
            rows.append({**r, "relation": rel, "part_a": "shaft", "part_b": "bore"})
    pairs = pairs_frame(rows)
    cad = pd.DataFrame({"scene": ["assembly-shaft"], "part_a": ["bore"], "part_b": ["shaft"],
                        "kinematic": ["revolute"]})  # stored the other way round
    joints = joint_frame(pairs, cad)
    assert joints[["cad_joint", "predicted_joint", "agree"]].values.tolist() == [
        ["revolute", "revolute", True]]
    cad["kinematic"] = "planar"
    assert not joint_frame(pairs, cad)["agree"].any()
    # a method with a joint head answers the joint itself: its answer is scored, not the rule
    headed = pairs_frame([{**r, "joint": "planar"} for r in rows])
    assert joint_frame(headed, cad)[["predicted_joint", "agree"]].values.tolist() == [
        ["planar", True]]
    # the other side: a pair without a CAD joint that is given one
    from reports.relations import false_joints

    loose = [{**r, "part_a": "shaft", "part_b": "cover"} for r in rows]
    assert false_joints(pairs_frame(rows + loose), cad) == (1, 1)
    assert false_joints(pairs_frame(rows + [{**r, "joint": "none"} for r in loose]),
                        cad) == (1, 0)


def test_calibration_error_is_zero_when_confidence_matches_accuracy() -> None:
    from reports.relations import expected_calibration_error

    rng = np.random.default_rng(0)
    conf = np.full(10_000, 0.8)
    assert expected_calibration_error(conf, rng.random(10_000) < 0.8) < 0.02
    assert abs(expected_calibration_error(conf, np.zeros(10_000, bool)) - 0.8) < 1e-9


def test_f1_against_the_cad_mates_puts_every_method_beside_the_product() -> None:
    from reports.relations import assembly_f1_table

    rows = (_rows("assembly-a", "ltn", [True, True, False], [True, False, False])
            + _rows("assembly-a", "geometric", [True, True, False], [True, True, True]))
    table = assembly_f1_table(pairs_frame(rows))
    assert table.loc["left", "completed/ltn"] == 2 / 3  # precision 1, recall 1/2
    assert table.loc["left", "completed/geometric"] == 0.8  # precision 2/3, recall 1
    assert assembly_f1_table(pairs_frame([])).empty


def test_the_joint_interval_resamples_pairs_not_views() -> None:
    """Eight views of one pair are one pair: the interval counts distinct pairs ((a, b) and
    (b, a) alike), holds the agreement, and is as wide as the pairs' disagreement makes it."""
    rows = []
    for k in range(4):  # four pairs seen 8 times each, in both orders; two always right
        for view in range(8):
            a, b = (f"p{k}", f"q{k}") if view % 2 else (f"q{k}", f"p{k}")
            rows.append({"assembly": "asm", "part_a": a, "part_b": b, "agree": k < 2})
    table = pd.DataFrame(rows)
    low, high, pairs = joint_interval(table)
    assert pairs == 4
    assert low <= table["agree"].mean() <= high
    # per view, 32 draws would give a narrow interval; four pairs leave it wide
    assert high - low >= 0.5
    everyone = table.assign(agree=True)
    assert joint_interval(everyone)[:2] == (1.0, 1.0)
    many = pd.concat([table.assign(assembly=f"asm{i}") for i in range(25)], ignore_index=True)
    low_many, high_many, pairs_many = joint_interval(many)
    assert pairs_many == 100 and high_many - low_many < (high - low) / 2
    assert joint_interval(table.iloc[:0])[2] == 0


def test_the_f1_interval_resamples_pairs_and_fills_the_assembly_table() -> None:
    """F1's interval counts distinct pairs (a pair seen in many views is one pair), holds the
    F1, narrows with more pairs, and is undefined where no resample has a positive."""
    from reports.relations import assembly_frame, f1_interval

    rows = []
    for k in range(6):  # six pairs, eight views each in both orders
        truth, predicted = k < 3, k in (0, 1, 3)  # two hits, one miss, one false mate
        for view in range(8):
            a, b = (f"p{k}", f"q{k}") if view % 2 else (f"q{k}", f"p{k}")
            rows.append({"scene": "assembly-x", "part_a": a, "part_b": b, "truth": truth,
                         "predicted": predicted})
    table = pd.DataFrame(rows)
    f1 = scores(table["truth"].to_numpy(), table["predicted"].to_numpy())["f1"]
    low, high, pairs = f1_interval(table)
    assert pairs == 6 and low <= f1 <= high and high - low >= 0.3
    many = pd.concat([table.assign(scene=f"assembly-{i}") for i in range(30)])
    low_many, high_many, pairs_many = f1_interval(many)
    assert pairs_many == 180 and high_many - low_many < (high - low) / 2
    empty = f1_interval(table.assign(truth=False, predicted=False))
    assert math.isnan(empty[0]) and math.isnan(empty[1]) and empty[2] == 6
    assert f1_interval(table.iloc[:0])[2] == 0
    frame = pairs_frame(_rows("assembly-a", "ltn", [True, True, False], [True, False, False]))
    left = assembly_frame(frame).set_index(["assembly", "relation"]).loc[("all", "left")]
    # three views of one pair: one pair, its F1 the only value a resample can take
    assert left["pairs"] == 1 and left["f1_low"] == left["f1"] == left["f1_high"]


def test_the_mates_f1_interval_averages_the_relations_of_each_draw() -> None:
    """With one relation it is that relation's F1 interval; with two it holds their mean F1
    and is no wider than the wider of the two."""
    from reports.intervals import f1_interval, mates_f1_interval

    rows = []
    for k in range(10):
        for rel, truth, predicted in (("concentric", k < 5, k < 4), ("coincident", k < 3,
                                                                     k in (0, 5, 6))):
            rows += [{"scene": "assembly-y", "part_a": f"a{k}", "part_b": f"b{k}",
                      "relation": rel, "truth": truth, "predicted": predicted}] * 3
    table = pd.DataFrame(rows)
    one = table[table["relation"] == "concentric"]
    assert mates_f1_interval(one) == f1_interval(one)
    low, high, pairs = mates_f1_interval(table)
    f1 = [scores(g["truth"].to_numpy(), g["predicted"].to_numpy())["f1"]
          for _, g in table.groupby("relation")]
    assert pairs == 10 and low <= float(np.mean(f1)) <= high
    widths = [f1_interval(g)[1] - f1_interval(g)[0] for _, g in table.groupby("relation")]
    assert high - low <= max(widths)
    assert mates_f1_interval(table.iloc[:0])[2] == 0
