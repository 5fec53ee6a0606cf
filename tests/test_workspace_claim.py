"""One night at a time per workspace, and only in a folder that is a workspace."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from conftest import finish_night, start_night

from cadio.catalog import read_catalog
from cadio.workspace_claim import (
    LOCK,
    MARKER,
    WorkspaceBusyError,
    claim_workspace,
    workspace_problem,
)

ROOT = Path(__file__).resolve().parents[1]
_HOLD = """
import sys, time
from pathlib import Path
from cadio.workspace_claim import claim_workspace
with claim_workspace(Path(sys.argv[1]), {"what": "mateqa nightly", "flow_run": "mini-chital"}):
    print("held", flush=True)
    time.sleep(600)
"""


@pytest.mark.parametrize("folder", ["/", "/usr", "/tmp", "/etc/", "~"])
def test_the_root_a_system_folder_or_the_home_is_never_a_workspace(folder: str) -> None:
    problem = workspace_problem(Path(folder).expanduser())
    assert problem is not None and ("filesystem root" in problem or "system folder" in problem)


def test_a_workspace_is_new_empty_or_one_already(tmp_path: Path) -> None:
    assert workspace_problem(tmp_path / "new") is None
    assert workspace_problem(tmp_path) is None  # empty
    (tmp_path / "runs").mkdir()
    (tmp_path / "catalog.parquet").write_bytes(b"")
    (tmp_path / ".epoch").write_text("x")
    assert workspace_problem(tmp_path) is None  # one an earlier version made: no marker yet
    (tmp_path / "thesis.tex").write_text("mine")
    assert "not empty and not a mateqa workspace (it holds thesis.tex)" in str(
        workspace_problem(tmp_path))
    (tmp_path / MARKER).write_text("")
    assert workspace_problem(tmp_path) is None  # marked: whatever else it holds
    (tmp_path / "runs" / "latest").mkdir()
    assert "runs/latest is not the link" in str(workspace_problem(tmp_path))


def test_a_second_claim_is_refused_naming_the_holder_until_it_dies(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(ws)], cwd=ROOT,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        with pytest.raises(WorkspaceBusyError) as err, claim_workspace(ws, {"what": "x"}):
            pass
        assert err.value.holder["pid"] == holder.pid
        assert f"in use by mateqa nightly (flow run 'mini-chital', pid {holder.pid} on " in \
            str(err.value)
    finally:
        holder.send_signal(signal.SIGKILL)  # no chance to let go: the kernel does
        holder.wait()
    with claim_workspace(ws, {"what": "mateqa ingest"}) as record:
        assert record["pid"] == os.getpid()
        assert json.loads((ws / LOCK).read_text())["what"] == "mateqa ingest"
    assert (ws / LOCK).read_text() == "" and (ws / MARKER).is_file()


@pytest.mark.server
def test_two_nights_on_one_workspace_never_mix(
        small_library: Path, prefect_api: dict[str, str], tmp_path: Path) -> None:
    other = tmp_path / "other-library" / "wheels"
    other.mkdir(parents=True)
    for step in (small_library / "couplings").iterdir():
        shutil.copy(step, other)
    ws = tmp_path / "ws"
    first = start_night(small_library, ws, prefect_api)
    lock = ws / LOCK
    deadline = time.monotonic() + 600
    while not (lock.is_file() and lock.read_text()):  # the first night holds the workspace
        assert first.poll() is None, first.log.read_text()[-3000:]
        assert time.monotonic() < deadline, "the first night never started"
        time.sleep(0.2)
    second = subprocess.run(  # as a user starts one by hand beside the scheduled one
        [sys.executable, "-m", "flows.cli", "nightly", "--library", str(other.parent),
         "--workspace", str(ws), "--views-per-scene", "1", "--pairs-per-relation", "1"],
        cwd=ROOT, env=prefect_api, capture_output=True, text=True, timeout=600)
    assert second.returncode == 2, second.stderr[-3000:]
    assert f"{ws} is in use by mateqa nightly (flow run '" in second.stderr
    assert "Traceback" not in second.stdout + second.stderr
    finish_night(first)
    categories = pd.read_csv(ws / "runs" / "latest" / "categories.csv")["category"]
    assert not categories.str.contains("wheels").any()  # none of the other library's
    assert "wheels" not in set(read_catalog(ws / "catalog.parquet")["category"])
