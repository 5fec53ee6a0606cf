"""The local Prefect server (flows/server.py), one story: a server started for a night has its
web UI and the runs' "View at" links open; a later night reuses it; `serve` replaces a headless
one; `serve --stop` stops the server on the port. Real servers on free loopback ports."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import psutil
import pytest
from conftest import ONE_THREAD, free_port

from flows.server import (
    DATABASE,
    PID_FILE,
    api_url,
    is_healthy,
    keep_template,
    server_env,
    start_server,
    stop_port,
    stop_server,
    template_database,
    ui_answers,
)

pytestmark = pytest.mark.server

_FLOW = """
from prefect import flow

@flow(name="hello")
def hello() -> int:
    return 1

hello()
"""


def _view_link(home: Path, port: int) -> str:
    """Run a one-task flow against the server; the "View at" link it logs."""
    done = subprocess.run([sys.executable, "-c", _FLOW], env=server_env(home, port),
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    found = re.search(r"View at (\S+)", done.stdout + done.stderr)
    assert found, done.stdout[-2000:] + done.stderr[-2000:]
    return found.group(1)


def _status(url: str) -> tuple[int, str]:
    """Status and content type of ``url`` opened as a browser does (asking for HTML)."""
    request = urllib.request.Request(url, headers={"Accept": "text/html,*/*;q=0.8"})
    try:
        with urllib.request.urlopen(request, timeout=10) as resp:
            return resp.status, resp.headers.get("content-type", "")
    except urllib.error.HTTPError as exc:
        return exc.code, ""


def test_a_night_server_has_its_ui_its_links_open_and_a_later_night_reuses_it(
        tmp_path: Path) -> None:
    home, port = tmp_path / "prefect", free_port()
    server = start_server(home, port, timeout_s=600)
    try:
        assert server.started and server.ui and ui_answers(port)
        assert (home / PID_FILE).read_text().strip() == str(server.pid)
        link = _view_link(home, port)
        assert link.startswith(f"http://127.0.0.1:{port}/runs/flow-run/")
        status, kind = _status(link)
        assert status == 200 and "text/html" in kind
        again = start_server(home, port)
        assert not again.started and again.left_by_mateqa and again.pid == server.pid
        stop_server(again)  # not started by that call: left running
        assert is_healthy(api_url(port))
    finally:
        stop_server(server)
    assert not is_healthy(api_url(port))
    assert not (home / PID_FILE).exists()


def test_a_headless_server_is_replaced_by_one_with_its_ui_and_stop_port_stops_it(
        tmp_path: Path) -> None:
    home, port = tmp_path / "prefect", free_port()
    headless = start_server(home, port, timeout_s=600, ui=False)
    try:
        assert headless.started and not ui_answers(port)
        status, _ = _status(_view_link(home, port))
        assert status == 404  # what a night's links gave before
        served = start_server(home, port, timeout_s=600)
        assert served.started and served.replaced == headless.pid and ui_answers(port)
        assert not psutil.pid_exists(headless.pid or -1)
        assert stop_port(port, home) == served.pid
        assert not is_healthy(api_url(port))
        assert not (home / PID_FILE).exists()
        assert stop_port(port, home) is None
    finally:
        stop_server(headless)
        stop_port(port)


def test_a_new_home_starts_from_the_kept_database_and_a_bad_copy_is_dropped(
        prefect_api: dict[str, str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("PREFECT_API_DATABASE_CONNECTION_URL", raising=False)
    template = template_database()
    keep_template(Path(prefect_api["PREFECT_HOME"]))  # a migrated database, its server running
    assert template.read_bytes().startswith(b"SQLite format 3")
    with contextlib.closing(sqlite3.connect(template)) as db:  # a mark only a copy has
        db.execute("CREATE TABLE probe (x)")
        db.commit()
    port = free_port()
    server = start_server(tmp_path / "second", port, timeout_s=600)
    try:
        assert server.started and is_healthy(api_url(port))
        with contextlib.closing(sqlite3.connect(tmp_path / "second" / DATABASE)) as db:
            assert db.execute("SELECT name FROM sqlite_master WHERE name = 'probe'").fetchone()
    finally:
        stop_server(server)
    template.write_bytes(b"not a database")
    server = start_server(tmp_path / "third", port, timeout_s=600)
    try:
        assert server.started and is_healthy(api_url(port))
    finally:
        stop_server(server)
    assert template.read_bytes().startswith(b"SQLite format 3")  # kept anew by the third


def test_stop_port_leaves_a_port_that_another_program_holds(tmp_path: Path) -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        port = sock.getsockname()[1]
        with pytest.raises(RuntimeError, match=f"port {port} is held by process"):
            stop_port(port)


# A stand-in for a night: a flow run labelled as a night labels its runs, running until its
# marker file is removed.
_NIGHT_STAND_IN = """
import sys, time
from pathlib import Path
from prefect import flow
from flows.stale_runs import label_flow_run

@flow(name="stand-in")
def stand_in(marker: str) -> None:
    label_flow_run()
    Path(marker).write_text("running")
    while Path(marker).exists():
        time.sleep(0.2)

stand_in(sys.argv[1])
"""
ROOT = Path(__file__).resolve().parents[1]


def _running_stand_in(home: Path, port: int, marker: Path) -> subprocess.Popen[bytes]:
    proc = subprocess.Popen([sys.executable, "-c", _NIGHT_STAND_IN, str(marker)], cwd=ROOT,
                            env=server_env(home, port), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while not marker.exists():
        assert proc.poll() is None and time.monotonic() < deadline, "the flow never ran"
        time.sleep(0.2)
    return proc


def test_a_server_in_use_is_not_stopped_and_a_killed_runs_are_marked_crashed(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL, temporary_settings

    from flows.cli import main
    from flows.stale_runs import crash_dead_runs, runs_in_flight

    home, port = tmp_path / "prefect", free_port()
    server = start_server(home, port, timeout_s=600)
    try:
        stand_in = _running_stand_in(home, port, tmp_path / "running")
        (name,) = runs_in_flight(api_url(port))
        stop = ["serve", "--stop", "--port", str(port), "--home", str(home)]
        assert main(stop) == 1
        assert f"not stopped: 1 flow run(s) in flight on it ({name})" in capsys.readouterr().err
        assert is_healthy(api_url(port))
        stand_in.send_signal(signal.SIGKILL)  # as the OOM killer does: it cannot mark itself
        stand_in.wait()
        assert crash_dead_runs(api_url(port)) == [name]
        with temporary_settings({PREFECT_API_URL: api_url(port)}), \
                get_client(sync_client=True) as client:
            (run,) = client.read_flow_runs()
        assert run.state is not None and run.state.name == "Crashed"
        assert f"(pid {stand_in.pid} on " in str(run.state.message) and "is gone" in str(
            run.state.message)
        assert main(stop) == 0 and not is_healthy(api_url(port))
    finally:
        stop_server(server)


def test_stop_server_leaves_the_server_to_a_night_that_uses_it(
        tmp_path: Path, box_step: Path, pin_step: Path) -> None:
    lib = tmp_path / "lib" / "fasteners"
    lib.mkdir(parents=True)
    shutil.copy(box_step, lib)
    shutil.copy(pin_step, lib)
    home, port = tmp_path / "prefect", free_port()
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    night = subprocess.Popen(
        [sys.executable, "-m", "flows.cli", "nightly", "--library", str(lib.parent),
         "--workspace", str(tmp_path / "ws"), "--voxel-sizes", "16", "--views-per-scene", "1",
         "--pairs-per-relation", "1", "--stop-server"], cwd=ROOT, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True,
        env={**env, "MATEQA_SERVER_PORT": str(port), "MATEQA_PREFECT_HOME": str(home),
             **ONE_THREAD})
    marker = tmp_path / "running"
    try:
        deadline = time.monotonic() + 600
        while not is_healthy(api_url(port)):  # the night starts the server
            assert night.poll() is None and time.monotonic() < deadline, night.communicate()
            time.sleep(0.5)
        other = _running_stand_in(home, port, marker)  # another night uses it meanwhile
        _, err = night.communicate(timeout=900)
        assert night.returncode == 0, err[-3000:]
        assert f"left the Prefect server on port {port} running: 1 flow run(s) in flight" in err
        assert is_healthy(api_url(port))
        marker.unlink()  # the other night ends, on a server that stayed up
        assert other.wait(120) == 0
    finally:
        marker.unlink(missing_ok=True)
        night.kill()
        stop_port(port)
