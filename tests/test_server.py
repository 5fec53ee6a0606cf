"""The local Prefect server (flows/server.py), one story: a server started for a night has its
web UI and the runs' "View at" links open; a later night reuses it; `serve` replaces a headless
one; `serve --stop` stops the server on the port. Real servers on free loopback ports."""

from __future__ import annotations

import contextlib
import re
import socket
import sqlite3
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import psutil
import pytest
from conftest import free_port

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
