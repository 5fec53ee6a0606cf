"""The verdict of a night: per category pass or fail from every check, its headline figures,
the failed inputs; in the report's first table and as the last dozen lines of
``mateqa nightly`` (a threshold failure prints it and exits 3, without a traceback)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from conftest import ONE_THREAD

from reports.html import verdict_table
from reports.run_report import write_run_report
from reports.trends import Limit, Thresholds, check_metrics
from reports.verdict import build_verdict, console_verdict, read_problems, read_verdict

IOU = "completion_iou_shapes"  # the completion headline: per distinct shape, as placed
LIMITS = Thresholds(limits={IOU: Limit(floor=0.3, max_drop=0.05),
                            "completion_fscore": Limit(floor=0.5),
                            "relation_accuracy": Limit(floor=0.8)}, min_n=10)
NO_PROBLEMS = pd.DataFrame(columns=["stage", "item", "status", "reason"])


def _metrics(rows: list[tuple[str, str, float, int]]) -> pd.DataFrame:
    return pd.DataFrame([{"category": c, "metric": m, "value": v, "n": n} for c, m, v, n in rows])


TONIGHT = _metrics([("fasteners", IOU, 0.45, 20),
                    ("fasteners", "completion_fscore", 0.40, 20),  # fails: not a headline figure
                    ("motion", IOU, 0.36, 12),  # regressed: 0.44 before
                    ("motion", "relation_accuracy", 0.95, 40),
                    ("brakes", IOU, 0.10, 3),  # too few to check
                    ("all", IOU, 0.40, 35), ("all", "relation_accuracy", 0.9, 40)])
LAST_NIGHT = _metrics([("motion", IOU, 0.44, 12), ("all", IOU, 0.41, 35)])


def test_a_category_fails_on_any_of_its_checks_and_shows_its_headline_figures() -> None:
    verdict = build_verdict("20260102T0Z", check_metrics(TONIGHT, [LAST_NIGHT], LIMITS),
                            NO_PROBLEMS)
    by_name = {c.category: c for c in verdict.categories}
    assert [c.category for c in verdict.categories] == ["brakes", "fasteners", "motion", "all"]
    assert by_name["fasteners"].status == "fail" and by_name["fasteners"].failed == 1
    fasteners_iou = by_name["fasteners"].figure(IOU)
    assert fasteners_iou is not None and fasteners_iou.status == "pass"
    assert by_name["fasteners"].figure("completion_fscore") is None  # not a headline metric
    assert by_name["motion"].status == "regressed" and by_name["brakes"].status == "too-few"
    assert by_name["all"].status == "pass" and by_name["all"].checked == 2
    motion_iou = by_name["motion"].figure(IOU)
    assert motion_iou is not None and motion_iou.previous == 0.44 and motion_iou.threshold == 0.3
    assert verdict.failed == (  # in the order of categories.csv: by metric
        "motion completion_iou_shapes regressed: 0.36 (previous 0.44, allowed drop 0.05)",
        "fasteners completion_fscore fail: 0.4 (floor 0.5)")
    assert not verdict.passed and verdict.checked == 6 and verdict.too_few == 1
    assert verdict.headline() == ("Night 20260102T0Z: FAIL, 2 of 6 threshold checks failed or "
                                  "regressed, 1 too few to check")
    first = build_verdict("20260101T0Z", check_metrics(LAST_NIGHT, [], LIMITS), NO_PROBLEMS)
    assert first.passed and first.headline().endswith("first night: no previous values")


def test_a_night_that_checked_nothing_does_not_pass(tmp_path: Path) -> None:
    """Every value too few to check, or without a threshold: the verdict says so, never PASS
    (a night over one recording it could not use once read "PASS, no threshold check")."""
    few = _metrics([("fasteners", IOU, 0.45, 3), ("all", "ingest_ok_fraction", 1.0, 1)])
    verdict = build_verdict("20260105T0Z", check_metrics(few, [], LIMITS), NO_PROBLEMS)
    assert not verdict.passed and not verdict.failed and verdict.word == "UNCHECKED"
    assert verdict.headline() == ("Night 20260105T0Z: UNCHECKED, no threshold check applied: "
                                  "this night checked nothing, 2 too few to check; first "
                                  "night: no previous values")
    run = tmp_path / "20260105T000000Z"
    run.mkdir()
    (run / "ingest.json").write_text(json.dumps({"totals": {"files": 1, "ok": 1}}))
    report = write_run_report(run, [], LIMITS)
    assert report.verdict == "UNCHECKED" and report.passed  # nothing failed: exit 0
    page = Path(report.html).read_text()
    assert "banner no-data'>Night 20260105T000000Z: UNCHECKED" in page
    assert console_verdict(run).startswith("Night 20260105T000000Z: UNCHECKED")


def test_the_verdict_says_where_its_floors_came_from(tmp_path: Path) -> None:
    from reports.trends import DEFAULT_THRESHOLDS, read_thresholds

    run = tmp_path / "20260106T000000Z"
    run.mkdir()
    write_run_report(run, [], LIMITS)  # floors given in code: no file to keep
    assert not (run / "thresholds.toml").exists() and "Floors" not in console_verdict(run)
    write_run_report(run, [], read_thresholds(DEFAULT_THRESHOLDS))
    assert (run / "thresholds.toml").read_bytes() == DEFAULT_THRESHOLDS.read_bytes()
    assert "  Floors: the shipped defaults" in console_verdict(run)
    mine = tmp_path / "mine.toml"
    mine.write_text("[completion_iou_shapes]\nfloor = 0.3\n")
    write_run_report(run, [], read_thresholds(mine))
    assert "  Floors: set by hand; see thresholds.toml in this run's folder" in \
        console_verdict(run).splitlines()
    mine.write_text('reference_run = "/ws/runs/20260101T000000Z"\n' + mine.read_text())
    report = write_run_report(run, [], read_thresholds(mine))
    assert "Floors: calibrated from the run 20260101T000000Z (/ws/runs/20260101T000000Z)" \
        in console_verdict(run)
    assert "Floors: calibrated from the run 20260101T000000Z" in Path(report.html).read_text()


def test_the_verdict_table_escapes_names_and_colours_each_cell_by_its_status() -> None:
    hostile = TONIGHT.replace({"category": {"fasteners": "<b onclick='x'>bolts</b>"}})
    table = verdict_table(build_verdict("r", check_metrics(hostile, [LAST_NIGHT], LIMITS),
                                        NO_PROBLEMS))
    assert "<b onclick" not in table and "&lt;b onclick=&#x27;x&#x27;&gt;bolts" in table
    assert "<td class='regressed'><b>0.360</b> regressed<br><small>floor 0.300 · prev 0.440" \
        in table
    assert "<td class='too-few'><b>0.100</b> too few (n=3)" in table


def _run_folder(root: Path) -> Path:
    """A run whose ingest lost one file and whose capture stage lost one capture."""
    run = root / "20260102T000000Z"
    run.mkdir(parents=True)
    (run / "ingest.json").write_text(json.dumps({
        "totals": {"files": 12, "ok": 11},
        "per_category": [{"category": "fasteners", "files": 12, "ok": 11}],
        "problems": [{"category": "fasteners", "source": "/lib/fasteners/bad.step",
                      "status": "failed", "error": "truncated STEP file"}]}))
    (run / "stages.json").write_text(json.dumps({"failures": [
        {"stage": "capture", "category": "", "item": "s0-test-left", "error": "no frames"}]}))
    return run


def test_the_console_verdict_is_a_dozen_lines_with_the_failed_inputs_and_the_report(
        tmp_path: Path) -> None:
    run = _run_folder(tmp_path)
    strict = Thresholds(limits={"ingest_ok_fraction": Limit(floor=0.95)}, min_n=10)
    report = write_run_report(run, [], strict)
    assert read_problems(run)["item"].tolist() == ["/lib/fasteners/bad.step", "s0-test-left"]
    text = console_verdict(run)
    lines = text.splitlines()
    assert 6 <= len(lines) <= 14, text
    assert lines[0] == ("Night 20260102T000000Z: FAIL, 2 of 2 threshold checks failed or "
                        "regressed; first night: no previous values")
    assert lines[1].split() == ["category", "verdict", "completion", "IoU", "per", "shape",
                                "relation", "accuracy", "ingest", "ok"]
    assert lines[2].split() == ["fasteners", "fail", "-", "-", "0.917", "fail"]
    assert "  failed: fasteners ingest_ok_fraction fail: 0.917 (floor 0.95)" in lines
    assert "Failed inputs: 2 (ingest 1, capture 1)" in text
    assert f"Report: {run.resolve() / 'report.html'}" in lines and Path(report.html).is_file()
    checks = pd.read_csv(run / "categories.csv")
    checks["category"] = checks["category"].replace({"fasteners": "bolts\nall pass\x1b[2J"})
    checks.to_csv(run / "categories.csv", index=False)
    hostile = console_verdict(run).splitlines()
    assert len(hostile) == len(lines) and "\x1b" not in "".join(hostile)
    assert hostile[2].split()[0] == "bolts\\nall"  # written as an escape, on its own line
    assert read_verdict(run).problem_counts() == "2 (ingest 1, capture 1)"


def test_a_threshold_failure_prints_the_verdict_and_exits_3_without_a_traceback(
        tmp_path: Path, prefect_api: dict[str, str], capsys: pytest.CaptureFixture[str]) -> None:
    import xml.etree.ElementTree as ET

    from test_flows import _gap_assembly

    from flows.cli import main

    lib = tmp_path / "lib" / "assemblies"
    lib.mkdir(parents=True)
    _gap_assembly(lib / "gap.step", 0.0)
    strict = tmp_path / "strict.toml"
    strict.write_text("min_n = 0\n[ingest_ok_fraction]\nfloor = 1.5\n")
    ws = tmp_path / "ws"

    def night(*extra: str) -> subprocess.CompletedProcess[str]:
        args = ["nightly", "--library", str(lib.parent), "--workspace", str(ws),
                "--voxel-sizes", "16", "--views-per-scene", "1", "--pairs-per-relation", "1",
                "--inspection-views", "1", "--no-inspection-defects", "--no-inspection-search",
                "--thresholds", str(strict), *extra]
        return subprocess.run([sys.executable, "-m", "flows.cli", *args], capture_output=True,
                              text=True, check=False, cwd=Path(__file__).parents[1],
                              env={**os.environ, **prefect_api, **ONE_THREAD},
                              timeout=900)

    failed = night()
    assert failed.returncode == 3, failed.stderr[-4000:]
    assert "Traceback" not in failed.stdout + failed.stderr, failed.stderr[-4000:]
    run = (ws / "runs" / "latest").resolve()
    verdict = failed.stdout.strip().splitlines()
    assert len(verdict) <= 14, failed.stdout
    assert verdict[0].startswith(f"Night {run.name}: FAIL, 2 of 2 threshold checks failed")
    assert verdict[2].split()[:2] == ["assemblies", "fail"] and verdict[3].split()[:2] == [
        "all", "fail"]
    assert "  failed: assemblies ingest_ok_fraction fail: 1 (floor 1.5)" in verdict
    assert "Failed inputs: none" in verdict and f"Report: {run / 'report.html'}" in verdict
    assert "ingest_ok_fraction fail" in failed.stderr  # the one-line reason of exit 3
    assert (run / "report.html").is_file() and (run / "summary.json").is_file()
    suite = ET.parse(run / "junit.xml").getroot().find("testsuite")
    assert suite is not None and int(suite.get("failures", "0")) >= 1

    rerun = night("--no-fail-on-threshold", "--json")  # cached: only the reports are new
    assert rerun.returncode == 0, rerun.stderr[-4000:]
    latest = (ws / "runs" / "latest").resolve()
    assert latest != run and json.loads(rerun.stdout) == json.loads(
        (latest / "summary.json").read_text())

    bad = tmp_path / "bad.toml"  # a thresholds file that names no limit: exit 2, no night
    bad.write_text("[iou]\n")
    assert main(["nightly", "--library", str(lib.parent), "--workspace", str(ws),
                 "--thresholds", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: unknown metric 'iou'" in err, err
    assert (ws / "runs" / "latest").resolve() == latest


def test_the_console_lists_pair_categories_only_where_they_failed(tmp_path: Path) -> None:
    singles = [("bolts", IOU, 0.5, 20), ("gears", IOU, 0.5, 20),
               ("shafts", IOU, 0.5, 20), ("all", IOU, 0.5, 60)]
    pairs = [("bolts+gears", "relation_accuracy", 0.95, 40),
             ("bolts+shafts", "relation_accuracy", 0.50, 40),  # fails the 0.8 floor
             ("gears+shafts", "relation_accuracy", 0.90, 4),  # too few to check
             ("nuts+bolts", "relation_accuracy", 0.90, 40)]  # "nuts" is no category: shown
    run = tmp_path / "20260103T000000Z"
    run.mkdir()
    check_metrics(_metrics(singles + pairs), [], LIMITS).to_csv(run / "categories.csv",
                                                                 index=False)
    text = console_verdict(run)
    shown = [line.split()[0] for line in text.splitlines()[2:] if line.startswith("  ")
             and len(line.split()) > 1 and line.split()[1] in ("pass", "fail", "too-few")]
    assert shown == ["bolts", "bolts+shafts", "gears", "nuts+bolts", "shafts", "all"], text
    assert "  2 pair categories (a+b) not shown: 1 pass, 1 too-few; every one is in " \
        "report.html" in text.splitlines()
    assert "  failed: bolts+shafts relation_accuracy fail: 0.5 (floor 0.8)" in text


def test_the_assembly_figures_come_with_intervals_over_their_distinct_pairs(
        tmp_path: Path) -> None:
    """The console and the page give the mates F1 and the joint agreement a 95% interval
    that counts distinct pairs; a run without assemblies says nothing of them."""
    from reports.verdict import assembly_intervals

    run = tmp_path / "20260104T000000Z"
    run.mkdir()
    assert assembly_intervals(run) == ""
    rows, joints = [], []
    for k in range(12):  # twelve assembly pairs, four views each; eight right, four wrong
        right = k < 8
        for view in range(4):
            for rel, truth in (("concentric", k % 2 == 0), ("coincident", k % 3 == 0)):
                rows.append({"scene": "assembly-x", "view": view, "part_a": f"a{k}",
                             "part_b": f"b{k}", "category": "c", "input": "completed",
                             "method": "ltn", "relation": rel, "truth": truth,
                             "predicted": truth if right else not truth, "confidence": 0.9,
                             "near_boundary": False})
            joints.append({"assembly": "assembly-x", "view": view, "part_a": f"b{k}",
                           "part_b": f"a{k}", "cad_joint": "revolute",
                           "predicted_joint": "revolute" if right else "none",
                           "agree": right})
    # the same pairs by another method: not the product, not counted
    rows += [dict(r, method="mlp", predicted=not r["predicted"]) for r in rows]
    pd.DataFrame(rows).to_parquet(run / "relations_pairs.parquet")
    pd.DataFrame(joints).to_csv(run / "assembly_joints.csv", index=False)
    said = assembly_intervals(run)
    assert said.startswith("95% intervals over the distinct pairs: mates F1 ")
    assert "(12 pairs)" in said and said.count("(12 pairs)") == 2, said
    mates_low, mates_high = (float(x) for x in said.split("mates F1 ")[1].split(" (")[0]
                             .split(" to "))
    joint_low, joint_high = (float(x) for x in said.split("joint agreement ")[1].split(" (")[0]
                             .split(" to "))
    assert joint_low <= 8 / 12 <= joint_high and joint_high - joint_low > 0.3
    assert 0 < mates_low < mates_high < 1
    check_metrics(_metrics([("all", IOU, 0.5, 40), ("all", "mates_f1", 0.7, 40),
                            ("all", "joint_agreement", 8 / 12, 48)]), [], LIMITS).to_csv(
        run / "categories.csv", index=False)
    assert f"    {said}" in console_verdict(run).splitlines()
    report = write_run_report(run, [], LIMITS)
    assert "95% intervals over the distinct pairs" in Path(report.html).read_text()
