"""A night killed with SIGKILL halfway and started again ends with the same report as an
uninterrupted night, and the flow runs the killed one left Running are marked Crashed."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pandas as pd
import pytest
from conftest import run_night, start_night
from test_bad_inputs import _flow_runs

pytestmark = pytest.mark.server

# Every figure of the run, by file; run-specific columns (ids, previous runs) are left out.
REPORT_FILES = {"completion_categories.csv": [], "relations_summary.csv": [],
                "assembly_mates.csv": [], "categories.csv": ["previous"]}


def _report(run: Path) -> dict[str, pd.DataFrame]:
    return {name: pd.read_csv(run / name).drop(columns=drop)
            for name, drop in REPORT_FILES.items()}


@pytest.fixture(scope="module")
def restarted(small_library: Path, prefect_api: dict[str, str],
              tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The workspace of a night killed with SIGKILL mid-capture, then run again to the end."""
    killed = tmp_path_factory.mktemp("killed")
    proc = start_night(small_library, killed, prefect_api)
    deadline = time.monotonic() + 600
    while not list((killed / "captures").glob("*.mcap")) and time.monotonic() < deadline:
        assert proc.poll() is None, "the night ended before it could be killed"
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGKILL)  # the flow and its CAD workers, mid-capture
    proc.wait()
    assert not list(killed.glob("runs/*/summary.json")), "killed after the run completed"
    run_night(small_library, killed, prefect_api)
    return killed


def test_a_killed_night_restarted_gives_the_uninterrupted_report(
        restarted: Path, local_night: Path) -> None:
    whole, resumed = _report(local_night), _report((restarted / "runs" / "latest").resolve())
    for name, table in whole.items():
        assert len(table) > 0, name
        pd.testing.assert_frame_equal(resumed[name], table, obj=name)


def test_the_runs_a_killed_night_left_running_are_marked_crashed(
        restarted: Path, prefect_api: dict[str, str]) -> None:
    runs = _flow_runs(prefect_api, restarted)
    assert len(runs) == 4  # the killed night and its stages, then the night that resumed it
    states = sorted(run.state.name for run in runs)
    assert states == ["Completed", "Completed", "Crashed", "Crashed"], states
    for run in runs:
        if run.state.name == "Crashed":
            assert "is gone: the night was killed" in run.state.message
