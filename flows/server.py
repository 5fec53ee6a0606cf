"""Start and stop a local Prefect server on SQLite for runs that have no API URL configured,
and the rest of a local installation for ``mateqa serve``: a process work pool, the deployments
of ``prefect.yaml`` and a worker.

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


def server_env(home: Path, port: int, ui: bool = False) -> dict[str, str]:
    """Environment for a local server and its clients: SQLite under ``home``, no telemetry
    (the web UI only when asked: ``mateqa serve``)."""
    env = dict(os.environ)
    env.update({
        "PREFECT_HOME": str(home.resolve()),
        "PREFECT_API_URL": api_url(port),
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "PREFECT_SERVER_API_HOST": "127.0.0.1",
        "PREFECT_SERVER_API_PORT": str(port),
        "PREFECT_UI_ENABLED": "true" if ui else "false",
        "PREFECT_LOGGING_LEVEL": env.get("PREFECT_LOGGING_LEVEL", "INFO"),
    })
    return env


def start_server(home: Path, port: int, timeout_s: float = 90.0,
                 ui: bool = False) -> subprocess.Popen[bytes] | None:
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
            env=server_env(home, port, ui), stdout=log_file, stderr=subprocess.STDOUT,
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
    stop_process(proc)


POOL = "mateqa"


def project_root() -> Path:
    """The folder holding ``prefect.yaml``: the current one if it has it, else the checkout
    this package was installed from."""
    here = Path.cwd()
    if (here / "prefect.yaml").is_file():
        return here
    return Path(__file__).resolve().parent.parent


def _prefect(args: list[str], env: dict[str, str], cwd: Path, log: Path) -> None:
    """Run one ``prefect`` command; its output goes to ``log``.

    Raises:
        RuntimeError: the command failed (the log is named).
    """
    with log.open("ab") as out:
        code = subprocess.call([sys.executable, "-m", "prefect", "--no-prompt", *args], env=env,
                               cwd=cwd, stdout=out, stderr=subprocess.STDOUT,
                               stdin=subprocess.DEVNULL)
    if code != 0:
        raise RuntimeError(f"`prefect {' '.join(args)}` failed (exit {code}); see {log}")


def apply_deployments(env: dict[str, str], root: Path, log: Path) -> None:
    """Create the process work pool (kept if it exists) and apply every deployment of
    ``root/prefect.yaml``."""
    if not (root / "prefect.yaml").is_file():
        raise RuntimeError(f"{root}: no prefect.yaml here")
    _prefect(["work-pool", "create", POOL, "--type", "process", "--overwrite"], env, root, log)
    _prefect(["deploy", "--all", "--prefect-file", str(root / "prefect.yaml")], env, root, log)


def start_worker(env: dict[str, str], root: Path, log: Path) -> subprocess.Popen[bytes]:
    """A process worker of the pool, in its own session so that stopping it stops its runs."""
    with log.open("ab") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "prefect", "worker", "start", "--pool", POOL, "--type",
             "process"], env=env, cwd=root, stdout=out, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, start_new_session=True)


def stop_process(proc: subprocess.Popen[bytes] | None, timeout_s: float = 20.0) -> int | None:
    """Ask a child to stop (SIGTERM), kill it when it does not; its exit code."""
    if proc is None:
        return None
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode
