"""The local Prefect server on SQLite, and the rest of a local installation for ``mateqa serve``:
a process work pool, the deployments of ``prefect.yaml`` and a worker.

One server story: a server mateqa starts (for a night or for ``serve``) has its web UI, so the
"View at" links of the runs open; a night leaves it running for the UI and later nights, and
``mateqa serve`` takes it over (Ctrl-C then stops it). A headless Prefect server found on the
port (one an older version left) is replaced by one with the UI, unless a flow run is in flight
on it. ``mateqa serve --stop`` stops whatever Prefect server answers on the port, and a night's
``--stop-server`` the one it started, unless flow runs are in flight on it (``runs_using``:
another night's, which would fail without it).

Prefect migrates a new home's empty SQLite database on its first start (about 25 s of CPU here). The
first migrated database of a Prefect version is kept (``template_database``) and a later new
home starts from a copy of it; a server that does not start from the copy starts again without.

Prefect's ``--background`` mode never drains its output pipes and dies, so the server runs as a
plain child process in its own session with output to a log file, and we wait for
``/api/health``. The pid of a server mateqa started is kept in ``HOME/mateqa-server.pid``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sqlite3
import subprocess
import sys
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

import psutil

logger = logging.getLogger(__name__)

PID_FILE = "mateqa-server.pid"
DATABASE = "prefect.db"  # Prefect's SQLite database under PREFECT_HOME (its default URL)
# States of a flow run that a replaced server would cut short.
_IN_FLIGHT = ["PENDING", "RUNNING", "CANCELLING"]


def api_url(port: int) -> str:
    return f"http://127.0.0.1:{port}/api"


def ui_url(port: int) -> str:
    return f"http://127.0.0.1:{port}"


@dataclass(frozen=True)
class LocalServer:
    """A Prefect server answering on a loopback port.

    ``started``: this process started it (on a free port, or in place of a headless one).
    ``left_by_mateqa``: an earlier mateqa command started it (its pid is in the home's pid
    file). ``replaced``: the pid of the headless server it replaced.
    """

    port: int
    pid: int | None
    ui: bool
    started: bool = False
    left_by_mateqa: bool = False
    replaced: int | None = None
    home: Path | None = None
    process: subprocess.Popen[bytes] | None = field(default=None, compare=False, repr=False)

    @property
    def api_url(self) -> str:
        return api_url(self.port)

    @property
    def ui_url(self) -> str | None:
        return ui_url(self.port) if self.ui else None


def is_healthy(url: str) -> bool:
    """True when a Prefect API answers at ``url``."""
    try:
        with urllib.request.urlopen(f"{url}/health", timeout=2) as resp:
            return bool(resp.status == 200)
    except OSError:
        return False


def api_problem(url: str) -> str | None:
    """Why no Prefect API answers at ``url`` (refused, unreachable, timed out), or None when
    one does (with any HTTP status: a server that asks for credentials answers)."""
    try:
        with urllib.request.urlopen(f"{url.rstrip('/')}/health", timeout=10):
            return None
    except urllib.error.HTTPError:
        return None
    except OSError as exc:
        return str(getattr(exc, "reason", None) or exc)


def ui_answers(port: int) -> bool:
    """True when the Prefect web UI answers on ``port`` (a headless server gives 404 there)."""
    try:
        with urllib.request.urlopen(f"{ui_url(port)}/", timeout=5) as resp:
            return resp.status == 200 and "text/html" in resp.headers.get("content-type", "")
    except OSError:
        return False


def in_flight_runs(port: int) -> int | None:
    """Flow runs pending or running on the server at ``port``; None when it does not say."""
    body = json.dumps({"flow_runs": {"state": {"type": {"any_": _IN_FLIGHT}}}}).encode()
    request = urllib.request.Request(f"{api_url(port)}/flow_runs/count", data=body,
                                     headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=10) as resp:
            return int(json.load(resp))
    except (OSError, ValueError):
        return None


def listener(port: int) -> psutil.Process | None:
    """The process listening on TCP ``port`` of this host, where it can be seen."""
    try:
        conns = psutil.net_connections(kind="tcp")
    except psutil.AccessDenied:
        return None
    for conn in conns:
        if conn.status == psutil.CONN_LISTEN and conn.laddr and conn.laddr.port == port \
                and conn.pid is not None:
            try:
                return psutil.Process(conn.pid)
            except psutil.NoSuchProcess:
                return None
    return None


def is_prefect_server(proc: psutil.Process) -> bool:
    """True when ``proc`` is ``prefect server start`` (or the uvicorn of Prefect's API)."""
    try:
        cmd = proc.cmdline()
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return False
    words = [Path(word).name for word in cmd]
    return ("prefect" in words and "server" in words and "start" in words) \
        or any("prefect.server.api.server" in word for word in cmd)


def start_server(home: Path, port: int, timeout_s: float = 300.0,
                 ui: bool = True) -> LocalServer:
    """The Prefect server on ``port``: the one answering there, else one started here.

    A server answering without its UI when ``ui`` is asked for is replaced by one with it, if
    it is a Prefect server of this host with no flow run in flight; otherwise it is kept (with
    a warning: its "View at" links do not open).

    Raises:
        RuntimeError: the server did not answer within ``timeout_s`` (its log is named).
    """
    if is_healthy(api_url(port)):
        proc = listener(port)
        mine = proc is not None and proc.pid == _marked_pid(home)
        has_ui = ui_answers(port)
        if has_ui or not ui:
            return LocalServer(port, proc.pid if proc else None, has_ui, left_by_mateqa=mine,
                               home=home)
        reason = _why_not_replace(port, proc)
        if reason:
            logger.warning("the Prefect server on port %d has no UI and is kept (%s): its "
                           "run links will not open", port, reason)
            return LocalServer(port, proc.pid if proc else None, False, left_by_mateqa=mine,
                               home=home)
        assert proc is not None
        old = proc.pid
        stop_pid(old)
        return _launch(home, port, timeout_s, ui, replaced=old)
    return _launch(home, port, timeout_s, ui)


def _why_not_replace(port: int, proc: psutil.Process | None) -> str | None:
    """Why the headless server on ``port`` may not be replaced, or None when it may."""
    if proc is None or not is_prefect_server(proc):
        return "its process is not a Prefect server of this host"
    runs = in_flight_runs(port)
    if runs is None:
        return "it did not say whether flow runs are in flight"
    if runs:
        return f"{runs} flow run(s) in flight on it"
    return None


def _launch(home: Path, port: int, timeout_s: float, ui: bool,
            replaced: int | None = None) -> LocalServer:
    home.mkdir(parents=True, exist_ok=True)
    fresh = not (home / DATABASE).exists()
    seeded = fresh and _seed_database(home)
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
        if is_healthy(api_url(port)):
            (home / PID_FILE).write_text(f"{proc.pid}\n")
            if fresh and not seeded:
                keep_template(home)
            return LocalServer(port, proc.pid, ui, started=True, replaced=replaced,
                               home=home, process=proc)
        if proc.poll() is not None:
            break
        time.sleep(0.5)
    proc.kill()
    proc.wait()
    if seeded:  # the copy may be at fault: drop it and migrate afresh
        logger.warning("the Prefect server did not start from the kept database %s; starting "
                       "it on a new one", template_database())
        template_database().unlink(missing_ok=True)
        (home / DATABASE).unlink(missing_ok=True)
        return _launch(home, port, timeout_s, ui, replaced)
    raise RuntimeError(f"Prefect server did not start on port {port}; see {log_path}")


def template_database() -> Path:
    """Where the first migrated database of this Prefect version is kept for new homes."""
    from importlib.metadata import version

    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "mateqa" / f"prefect-{version('prefect')}.db"


def _seed_database(home: Path) -> bool:
    """Give a new home a copy of the kept database; True when it got one.

    Not where the environment points Prefect at another database, which the copy would not be.
    """
    template = template_database()
    if "PREFECT_API_DATABASE_CONNECTION_URL" in os.environ or not template.is_file():
        return False
    tmp = home / f"{DATABASE}.{os.getpid()}.tmp"
    try:
        tmp.write_bytes(template.read_bytes())
        os.replace(tmp, home / DATABASE)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        logger.debug("cannot copy %s into %s: %s", template, home, exc)
        return False
    return True


def keep_template(home: Path) -> None:
    """Keep a consistent copy of a home's just migrated database, unless one is kept already."""
    db, template = home / DATABASE, template_database()
    if template.exists() or not db.is_file():
        return
    tmp = template.with_name(f"{template.name}.{os.getpid()}.tmp")
    try:
        template.parent.mkdir(parents=True, exist_ok=True)
        with contextlib.closing(sqlite3.connect(db)) as src, \
                contextlib.closing(sqlite3.connect(tmp)) as dst:
            src.backup(dst)  # consistent while the server writes
            dst.execute("PRAGMA journal_mode=DELETE")  # one file, whole once closed
        os.replace(tmp, template)
    except (OSError, sqlite3.Error) as exc:
        tmp.unlink(missing_ok=True)
        logger.debug("cannot keep %s as %s: %s", db, template, exc)


def _marked_pid(home: Path) -> int | None:
    try:
        return int((home / PID_FILE).read_text().strip())
    except (OSError, ValueError):
        return None


def stop_server(server: LocalServer | None) -> None:
    """Stop a server that ``start_server`` started (no-op for None or one found running)."""
    if server is not None and server.started and server.pid is not None:
        _stop_and_unmark(server)


def stop_unless_used(server: LocalServer | None) -> str | None:
    """``stop_server``, unless flow runs are in flight on the server (another night's, which
    would fail without it): then why it was left running (``runs_using``)."""
    busy = runs_using(server.port) if server is not None and server.started else None
    if not busy:
        stop_server(server)
    return busy


def runs_using(port: int) -> str | None:
    """The flow runs in flight on the server at ``port`` (after marking Crashed those of
    nights whose process is gone: ``flows.stale_runs``), in words; None when there are none
    or no server answers."""
    from flows.stale_runs import runs_in_flight

    if not is_healthy(api_url(port)):
        return None
    names = runs_in_flight(api_url(port))
    if not names:
        return None
    return (f"{len(names)} flow run(s) in flight on it ({', '.join(names[:5])}"
            f"{' ...' if len(names) > 5 else ''})")


def stop_owned(server: LocalServer) -> None:
    """Stop the server when mateqa started it, now or for an earlier night (``serve``'s exit)."""
    if (server.started or server.left_by_mateqa) and server.pid is not None:
        _stop_and_unmark(server)


def _stop_and_unmark(server: LocalServer) -> None:
    assert server.pid is not None
    if server.process is not None:
        stop_process(server.process)
    else:
        stop_pid(server.pid)
    if server.home is not None and _marked_pid(server.home) == server.pid:
        (server.home / PID_FILE).unlink(missing_ok=True)


def stop_port(port: int, home: Path | None = None) -> int | None:
    """Stop the Prefect server listening on ``port`` of this host (``mateqa serve --stop``).

    Returns:
        Its pid, or None when no server answers there.

    Raises:
        RuntimeError: the port is held by a process that is no Prefect server, or one that
            cannot be seen, or flow runs are in flight on the server (``runs_using``).
    """
    proc = listener(port)
    if proc is None:
        if is_healthy(api_url(port)):
            raise RuntimeError(f"a Prefect API answers on port {port}, but its process cannot "
                               "be seen from here (another user's, or in a container)")
        return None
    if not is_prefect_server(proc):
        raise RuntimeError(f"port {port} is held by process {proc.pid} "
                           f"({' '.join(proc.cmdline())[:80]}), not a Prefect server")
    busy = runs_using(port)
    if busy:
        raise RuntimeError(f"the Prefect server on port {port} is not stopped: {busy}; stop "
                           "it once they end (a run that a killed night of an earlier mateqa left "
                           "Running can be set Crashed in the UI)")
    stop_pid(proc.pid)
    if home is not None and _marked_pid(home) == proc.pid:
        (home / PID_FILE).unlink(missing_ok=True)
    return int(proc.pid)


def stop_pid(pid: int, timeout_s: float = 20.0) -> None:
    """SIGTERM a process, SIGKILL it when it is still there after ``timeout_s``."""
    try:
        proc = psutil.Process(pid)
        proc.terminate()
        if not _ended(proc, timeout_s):
            proc.kill()
            _ended(proc, timeout_s)
    except psutil.NoSuchProcess:
        return


def _ended(proc: psutil.Process, timeout_s: float) -> bool:
    """Wait until ``proc`` has ended; a zombie has (its parent reaps it when it will: a server
    a night left behind belongs to no living process of ours)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            proc.wait(0.5)
            return True
        except psutil.TimeoutExpired:
            try:
                if proc.status() == psutil.STATUS_ZOMBIE:
                    return True
            except psutil.NoSuchProcess:
                return True
    return False


def server_env(home: Path, port: int, ui: bool = True) -> dict[str, str]:
    """Environment for a local server and its clients: SQLite under ``home``, no telemetry,
    the web UI on unless asked otherwise."""
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
