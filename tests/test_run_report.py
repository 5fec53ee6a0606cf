"""The run report: metrics per category against thresholds and earlier runs, JUnit XML, the
report files of a run with and without data."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import pandas as pd
import pytest

from reports.run_report import previous_runs, write_run_report
from reports.trends import (
    DEFAULT_THRESHOLDS,
    METRICS,
    Limit,
    Thresholds,
    ThresholdsError,
    check_metrics,
    read_thresholds,
    write_junit,
)


def _metrics(iou: float, accuracy: float, n: int = 50) -> pd.DataFrame:
    return pd.DataFrame([
        {"category": "fasteners", "metric": "completion_iou", "value": iou, "n": n},
        {"category": "all", "metric": "completion_iou", "value": iou, "n": n},
        {"category": "all", "metric": "relation_accuracy", "value": accuracy, "n": n},
        {"category": "all", "metric": "completion_chamfer_l1", "value": 3.0, "n": n}])


LIMITS = Thresholds(
    limits={"completion_iou": Limit(floor=0.3, max_drop=0.05),
            "relation_accuracy": Limit(floor=0.8),
            "completion_chamfer_l1": Limit(floor=2.5)},
    categories={"completion_iou": {"fasteners": Limit(floor=0.5)}})


def _status(checks: pd.DataFrame, category: str, metric: str) -> str:
    row = checks[(checks["category"] == category) & (checks["metric"] == metric)]
    return str(row["status"].iloc[0])


def test_checks_pass_fail_regress_and_follow_the_direction_of_each_metric() -> None:
    previous = _metrics(iou=0.45, accuracy=0.9)
    checks = check_metrics(_metrics(iou=0.38, accuracy=0.85), [previous], LIMITS)
    assert list(checks.columns[:6]) == ["category", "metric", "value", "previous", "threshold",
                                        "status"]
    assert _status(checks, "fasteners", "completion_iou") == "fail"  # per-category floor 0.5
    assert _status(checks, "all", "completion_iou") == "regressed"  # dropped 0.07 > 0.05
    assert _status(checks, "all", "relation_accuracy") == "pass"
    assert _status(checks, "all", "completion_chamfer_l1") == "fail"  # lower is better: 3 > 2.5
    row = checks[(checks["category"] == "all") & (checks["metric"] == "completion_iou")]
    assert row["previous"].iloc[0] == pytest.approx(0.45)
    assert row["threshold"].iloc[0] == pytest.approx(0.3)
    steady = check_metrics(_metrics(iou=0.44, accuracy=0.9), [previous], LIMITS)
    assert _status(steady, "all", "completion_iou") == "pass"


def test_a_drop_on_another_sample_is_held_to_the_draw_s_spread_on_the_same_to_max_drop() -> None:
    """A small pair category whose pair scenes were drawn anew (a part joined the library)
    moves by the draw alone: 0.875 -> 0.829 over 24 pair views is no regression; on the
    same sample the same drop is one (the code or the models changed); a fall past the draw's
    spread is one on any sample."""
    def night(accuracy: float, scenes: range) -> pd.DataFrame:
        sample = frozenset((f"s{k}", "0", "a", "b") for k in scenes)
        return pd.DataFrame([{"category": "a+b", "metric": "relation_accuracy",
                              "value": accuracy, "n": 24, "sample": sample}])

    limits = Thresholds(limits={"relation_accuracy": Limit(floor=0.7, max_drop=0.03)})
    old, new, most = range(24), range(100, 124), range(3, 27)
    moved = check_metrics(night(0.829, new), [night(0.875, old)], limits)
    assert moved["status"].tolist() == ["pass"] and moved["resampled"].tolist() == [1.0]
    assert moved["max_drop"].iloc[0] == pytest.approx(0.03 + 2 * math.sqrt(
        0.875 * 0.125 * 2 / 24))
    same = check_metrics(night(0.829, old), [night(0.875, old)], limits)
    assert same["status"].tolist() == ["regressed"] and same["resampled"].tolist() == [0.0]
    # three pair views of 24 drawn anew move the mean less: a drop of 0.115 regresses there
    few = check_metrics(night(0.76, most), [night(0.875, old)], limits)
    assert few["status"].tolist() == ["regressed"]
    assert few["resampled"].iloc[0] == pytest.approx(3 / 24)
    fell = check_metrics(night(0.60, new), [night(0.875, old)],
                         Thresholds(limits={"relation_accuracy": Limit(max_drop=0.03)}))
    assert fell["status"].tolist() == ["regressed"]


def test_a_run_s_samples_name_what_each_figure_was_measured_on(tmp_path: Path) -> None:
    """A category's sample changes when one of its pair views does, not when another
    category's does."""
    from reports.methods import product
    from reports.trends import run_samples

    given, method = product()
    rows = [{"scene": f"s{k}", "view": 0, "part_a": "p", "part_b": f"q{k}", "category": c,
             "input": given, "method": method} for k, c in enumerate(["a+b", "a+b", "c+d"])]
    pd.DataFrame(rows).to_parquet(tmp_path / "relations_pairs.parquet")
    first = run_samples(tmp_path)
    rows[0]["part_b"] = "other"
    pd.DataFrame(rows).to_parquet(tmp_path / "relations_pairs.parquet")
    second = run_samples(tmp_path)
    key = ("a+b", "relation_accuracy")
    assert first[key] != second[key] and first[("all", "relation_accuracy")] != \
        second[("all", "relation_accuracy")]
    assert first[("c+d", "relation_accuracy")] == second[("c+d", "relation_accuracy")]


def test_few_samples_no_threshold_and_vanished_categories_are_reported_not_checked() -> None:
    current = _metrics(iou=0.1, accuracy=0.1, n=3)
    checks = check_metrics(current, [], Thresholds(LIMITS.limits, LIMITS.categories, min_n=10))
    assert set(checks["status"]) == {"too-few"}
    gone = check_metrics(_metrics(0.5, 0.9).iloc[1:], [_metrics(0.5, 0.9)], LIMITS)
    assert _status(gone, "fasteners", "completion_iou") == "no-data"
    loose = check_metrics(_metrics(0.5, 0.9), [], Thresholds())
    assert set(loose["status"]) == {"no-threshold"}
    assert math.isnan(float(loose["previous"].iloc[0]))


def test_junit_has_one_case_per_category_and_metric_and_counts_failures(tmp_path: Path) -> None:
    checks = check_metrics(_metrics(iou=0.38, accuracy=0.85), [_metrics(0.45, 0.9)], LIMITS)
    root = ET.parse(write_junit(tmp_path / "junit.xml", checks, "nightly")).getroot()
    suite = root.find("testsuite")
    assert suite is not None
    cases = suite.findall("testcase")
    assert len(cases) == len(checks) == int(suite.get("tests", "0"))
    failed = {(c.get("classname"), c.get("name")) for c in cases if c.find("failure") is not None}
    assert failed == {("fasteners", "completion_iou"), ("all", "completion_iou"),
                      ("all", "completion_chamfer_l1")}
    assert int(suite.get("failures", "0")) == 3


def test_the_shipped_thresholds_read_and_bad_files_name_themselves(tmp_path: Path) -> None:
    shipped = read_thresholds(DEFAULT_THRESHOLDS)
    assert set(shipped.limits) <= set(METRICS) and shipped.limit("completion_iou_shapes", "x").floor
    cases = {"unknown.toml": ("[iou]\nfloor = 1\n", "unknown metric 'iou'"),
             "text.toml": ("[completion_iou]\nfloor = 'high'\n", "must be a finite number"),
             "broken.toml": ("[completion_iou\n", "cannot read thresholds")}
    for name, (text, reason) in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(ThresholdsError, match=f"{name}.*{reason}"):
            read_thresholds(tmp_path / name)


def test_a_run_without_completion_or_assemblies_still_reports(tmp_path: Path) -> None:
    run = tmp_path / "runs" / "20260101T000000Z"
    run.mkdir(parents=True)
    (run / "ingest.json").write_text('{"per_category": [], "totals": {"files": 0}}')
    report = write_run_report(run, [], read_thresholds(DEFAULT_THRESHOLDS))
    page = Path(report.html).read_text()
    assert "no completion scores in this run" in page and "no relation scores" in page
    assert report.passed and pd.read_csv(report.categories).empty
    assert pd.read_parquet(report.parts).empty and pd.read_parquet(report.pairs).empty


def test_previous_runs_are_the_completed_ones_before_this_run(tmp_path: Path) -> None:
    for name, done in [("20260101T0Z", True), ("20260102T0Z", False), ("20260103T0Z", True),
                       ("20260104T0Z", True), ("20260105T0Z", True)]:
        (tmp_path / name).mkdir()
        if done:
            (tmp_path / name / "summary.json").write_text("{}")
    names = [p.name for p in previous_runs(tmp_path, "20260105T0Z", 2)]
    assert names == ["20260103T0Z", "20260104T0Z"]
    assert previous_runs(tmp_path, "20260105T0Z", 0) == []
