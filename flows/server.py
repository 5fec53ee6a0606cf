"""Start and stop a local Prefect server on SQLite for runs that have no API URL configured.

Prefect's ``--background`` mode never drains its output pipes and dies, so the server runs as a
plain child process with output to a log file, and we wait for ``/api/health``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path


def api_url(port: int) -> str:
    return f"http://127.0.0.1:{port}/api"


def is_healthy(url: str) -> bool:
    """True when a Prefect API answers at ``url``."""
    try:
        with urllib.request.urlopen(f"{url}/health", timeout=2) as resp:
            return bool(resp.status == 200)
    except OSError:
        return False


def server_env(home: Path, port: int) -> dict[str, str]:
    """Environment for a local server and its clients: SQLite under ``home``, no telemetry."""
    env = dict(os.environ)
    env.update({
        "PREFECT_HOME": str(home.resolve()),
        "PREFECT_API_URL": api_url(port),
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "PREFECT_SERVER_API_HOST": "127.0.0.1",
        "PREFECT_SERVER_API_PORT": str(port),
        "PREFECT_UI_ENABLED": "false",
        "PREFECT_LOGGING_LEVEL": env.get("PREFECT_LOGGING_LEVEL", "INFO"),
    })
    return env


def start_server(home: Path, port: int, timeout_s: float = 90.0) -> subprocess.Popen[bytes] | None:
    """Start ``prefect server start`` unless one already answers; wait until healthy.

    Returns:
        The server process, or None when a server was already running on ``port``.

    Raises:
        RuntimeError: the server did not answer within ``timeout_s`` (its log is named).
    """
    url = api_url(port)
    if is_healthy(url):
        return None
    home.mkdir(parents=True, exist_ok=True)
    log_path = home / "server.log"
    with log_path.open("ab") as log_file:
        proc = subprocess.Popen(
            [sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1",
             "--port", str(port)],
            env=server_env(home, port), stdout=log_file, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, start_new_session=True,
        )
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if is_healthy(url):
            return proc
        if proc.poll() is not None:
            break
        time.sleep(0.5)
    proc.kill()
    raise RuntimeError(f"Prefect server did not start on port {port}; see {log_path}")


def stop_server(proc: subprocess.Popen[bytes] | None) -> None:
    """Stop a server started by ``start_server`` (no-op for None)."""
    if proc is None:
        return
    proc.terminate()
    try:
        proc.wait(20)
    except subprocess.TimeoutExpired:
        proc.kill()
