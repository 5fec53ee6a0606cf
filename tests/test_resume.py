"""A night killed with SIGKILL halfway and started again ends with the same report as an
uninterrupted night; the second night over an unchanged library redoes no work."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pandas as pd
import pytest
from conftest import finish_night, start_night

pytestmark = pytest.mark.server

# Every figure of the run, by file; run-specific columns (ids, previous runs) are left out.
REPORT_FILES = {"completion_categories.csv": [], "relations_summary.csv": [],
                "assembly_mates.csv": [], "categories.csv": ["previous"]}


def _report(run: Path) -> dict[str, pd.DataFrame]:
    return {name: pd.read_csv(run / name).drop(columns=drop)
            for name, drop in REPORT_FILES.items()}


def test_a_killed_night_restarted_gives_the_uninterrupted_report(
        small_library: Path, prefect_api: dict[str, str], local_night: Path,
        tmp_path: Path) -> None:
    killed = tmp_path / "killed"
    proc = start_night(small_library, killed, prefect_api)
    deadline = time.monotonic() + 600
    while not list((killed / "captures").glob("*.mcap")) and time.monotonic() < deadline:
        assert proc.poll() is None, "the night ended before it could be killed"
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGKILL)  # the flow and its CAD workers, mid-capture
    proc.wait()
    assert not list(killed.glob("runs/*/summary.json")), "killed after the run completed"

    finish_night(start_night(small_library, killed, prefect_api))
    whole, resumed = _report(local_night), _report((killed / "runs" / "latest").resolve())
    for name, table in whole.items():
        assert len(table) > 0, name
        pd.testing.assert_frame_equal(resumed[name], table, obj=name)
