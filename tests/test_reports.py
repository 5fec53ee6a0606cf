"""Tests of reports/: the per-category tables, the run's report files, and the room's imports."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from cadio.catalog import CatalogRow, to_frame
from cadio.contracts import CaptureSummary, MatesSummary
from reports.render import (
    build_ingest_report,
    build_stage_report,
    write_ingest_report,
    write_stage_report,
)
from reports.tables import captures_table, joints_table, markdown_table, mates_table


def _catalog() -> pd.DataFrame:
    ok = dict(status="ok", source_sha256="s", solid_index=0, n_solids=1)
    return to_frame([
        CatalogRow(part_id="a-0", category="fasteners", source="f/a.step", volume=10.0,
                   volume_rel_error=-0.004, **ok),
        CatalogRow(part_id="b-0", category="fasteners", source="f/b.step", volume=10.0,
                   volume_rel_error=0.02, cached=True, warning="1 face(s) could not be meshed",
                   **ok),
        CatalogRow(part_id="c-x", category="fasteners", source="f/c.step",
                   error="truncated STEP file"),
        CatalogRow(part_id="d-x", category="motion", source="m/d.step", status="skipped",
                   error="is a directory, not a STEP file"),
    ])


def test_ingest_report_counts_every_file_once() -> None:
    report = build_ingest_report(_catalog())
    t = report.totals
    assert (t.files, t.ok, t.failed, t.skipped, t.parts, t.cached) == (4, 2, 1, 1, 2, 1)
    assert t.ok + t.failed + t.skipped == t.files
    assert t.worst_volume_error_pct == pytest.approx(2.0)
    per = report.per_category.set_index("category")
    assert per.loc["fasteners", "files"] == 3 and per.loc["motion", "skipped"] == 1
    text = report.markdown()
    assert "truncated STEP file" in text and "is a directory" in text
    assert "could not be meshed" in text


def test_ingest_report_of_an_empty_catalog() -> None:
    t = build_ingest_report(to_frame([])).totals
    assert (t.files, t.parts, t.worst_volume_error_pct) == (0, 0, 0.0)


def _mates() -> list[MatesSummary]:
    return [
        MatesSummary("a1", "assemblies", "a1.step", "ok", n_parts=3, n_pairs=3, face_mates=4,
                     relations=6, joints=2, joint_types={"revolute": 1, "fastened": 1}),
        MatesSummary("a2", "assemblies", "a2.step", "ok", n_parts=2, n_pairs=1, face_mates=1,
                     relations=2, joints=1, joint_types={"revolute": 1}),
        MatesSummary("a3", "motion", "a3.step", "failed", error="timed out after 300 s"),
    ]


def test_mates_and_joints_tables_sum_per_category() -> None:
    table = mates_table(_mates()).set_index("category")
    assert table.loc["assemblies"].tolist() == [2, 0, 5, 4, 0, 5, 8, 3]
    assert table.loc["motion", "failed"] == 1 and table.loc["motion", "face_mates"] == 0
    joints = joints_table(_mates())
    assert joints.set_index("joint")["count"].to_dict() == {"fastened": 1, "revolute": 2}


def test_a_pair_capture_counts_in_both_categories() -> None:
    scenes = pd.DataFrame({"scene_id": ["s1", "s2"], "category_a": ["fasteners", "motion"],
                           "category_b": ["motion", "motion"]})
    captures = [CaptureSummary("s1", "s1.mcap", frames=8, bytes=2_000_000),
                CaptureSummary("s2", "s2.mcap", frames=8, bytes=1_000_000, error="bad"),
                CaptureSummary("real", "real.mcap", frames=3, bytes=10)]
    table = captures_table(captures, scenes).set_index("category")
    assert table.loc["fasteners", "part_views"] == 8
    assert table.loc["motion", "part_views"] == 8  # s2 failed: its views do not count
    assert table.loc["motion", "failed"] == 1 and table.loc["motion", "captures"] == 2
    assert table.loc["unknown", "frames"] == 3


def test_captures_of_no_scene_count_in_their_scored_parts_categories() -> None:
    """An assembly as placed and a part alone are filed under the categories of the parts they
    scored, not "unknown"."""
    captures = [CaptureSummary("assembly-press", "a.mcap", frames=4,
                               scored=("bolt-0", "bolt-1", "plate-0")),
                CaptureSummary("alone-plate-0", "b.mcap", frames=2, scored=("plate-0",)),
                CaptureSummary("alone-gone", "c.mcap", frames=2, error="unreadable")]
    categories = {"bolt-0": "fasteners", "bolt-1": "fasteners", "plate-0": "plates"}
    table = captures_table(captures, pd.DataFrame(columns=["scene_id", "category_a",
                                                           "category_b"]), categories)
    table = table.set_index("category")
    assert table.loc["fasteners", "part_views"] == 8 and table.loc["fasteners", "captures"] == 1
    assert table.loc["plates", "part_views"] == 6 and table.loc["plates", "captures"] == 2
    assert table.loc["unknown", "failed"] == 1 and table.loc["unknown", "part_views"] == 0


def test_stage_report_files_round_trip(tmp_path: Path) -> None:
    scenes = pd.DataFrame({"scene_id": ["s1"], "split": ["train"], "intended": ["left"],
                           "left": [True], "category_a": ["fasteners"],
                           "category_b": ["fasteners"]})
    captures = [CaptureSummary("s1", "s1.mcap", frames=2, input_parts=2)]
    report = build_stage_report(_mates(), scenes, captures)
    assert report.totals.assemblies == 3 and report.totals.assemblies_failed == 1
    assert report.totals.frames == 2 and report.totals.input_parts == 2
    md = write_stage_report(tmp_path, report)
    text = md.read_text()
    assert "## Failures" in text and "timed out after 300 s" in text
    data = json.loads((tmp_path / "stages.json").read_text())
    assert data["totals"]["face_mates"] == 5
    assert math.isnan(data["captures_detail"][0]["seg_mean_iou"])
    write_ingest_report(tmp_path, build_ingest_report(_catalog()))
    assert json.loads((tmp_path / "ingest.json").read_text())["totals"]["files"] == 4


def test_stage_report_without_scenes() -> None:
    report = build_stage_report([], None, [])
    assert report.totals.scenes == 0 and report.failures.empty
    assert "## Scenes" in report.markdown()


def test_markdown_table_escapes_pipes_newlines_and_markup() -> None:
    text = markdown_table(pd.DataFrame({"a": ["x|y", "two\nlines <b>"], "b|c": [1, 2]}))
    assert text.splitlines() == ["| a | b\\|c |", "|---|---|", "| x\\|y | 1 |",
                                 "| two\\nlines &lt;b&gt; | 2 |"]


def test_reports_import_no_cad_kernel_torch_or_renderer() -> None:
    code = ("import sys, reports.render, reports.tables, reports.metrics, reports.completion; "
            "print(sorted(m for m in ('OCP', 'torch', 'open3d', 'prefect', 'build123d') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=Path(__file__).resolve().parents[1])
    assert out.stdout.strip() == "[]"
