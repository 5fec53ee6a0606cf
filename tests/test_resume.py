"""A night killed with SIGKILL halfway and started again ends with the same report as an
uninterrupted night; the second night over an unchanged library redoes no work."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

pytestmark = pytest.mark.server

ROOT = Path(__file__).resolve().parents[1]
# Every figure of the run, by file; run-specific columns (ids, previous runs) are left out.
REPORT_FILES = {"completion_categories.csv": [], "relations_summary.csv": [],
                "assembly_mates.csv": [], "categories.csv": ["previous"]}


def _night(library: Path, workspace: Path, env: dict[str, str]) -> subprocess.Popen[bytes]:
    code = (f"from flows.nightly import nightly; nightly(library={str(library)!r}, "
            f"workspace={str(workspace)!r}, views_per_scene=2, pairs_per_relation=1, "
            "fail_on_threshold=False)")
    return subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                            start_new_session=True)


def _finish(proc: subprocess.Popen[bytes]) -> None:
    assert proc.wait(900) == 0


def _report(workspace: Path) -> dict[str, pd.DataFrame]:
    run = (workspace / "runs" / "latest").resolve()
    return {name: pd.read_csv(run / name).drop(columns=drop)
            for name, drop in REPORT_FILES.items()}


def test_a_killed_night_restarted_gives_the_uninterrupted_report(
        small_library: Path, prefect_api: dict[str, str], tmp_path: Path) -> None:
    env = {**prefect_api, "OMP_NUM_THREADS": "1"}
    _finish(_night(small_library, tmp_path / "whole", env))

    killed = tmp_path / "killed"
    proc = _night(small_library, killed, env)
    deadline = time.monotonic() + 600
    while not list((killed / "captures").glob("*.mcap")) and time.monotonic() < deadline:
        assert proc.poll() is None, "the night ended before it could be killed"
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGKILL)  # the flow and its CAD workers, mid-capture
    proc.wait()
    assert not list(killed.glob("runs/*/summary.json")), "killed after the run completed"

    _finish(_night(small_library, killed, env))
    whole, resumed = _report(tmp_path / "whole"), _report(killed)
    for name, table in whole.items():
        assert len(table) > 0, name
        pd.testing.assert_frame_equal(resumed[name], table, obj=name)
