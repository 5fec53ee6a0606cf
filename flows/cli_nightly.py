"""``mateqa nightly`` (the nightly flow, against a Prefect server) and ``mateqa serve`` (a
local server, work pool, worker and the deployments)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from flows.server import LocalServer

# Prefect configures its own loggers when imported; this override (a default the user's
# environment may replace) keeps one "Finished in state Completed()" per task off the console:
# the flow logs one line per stage instead.
_PREFECT_QUIET = {"PREFECT_LOGGING_LOGGERS_PREFECT_TASK_RUNS_LEVEL": "WARNING"}


def cmd_nightly(args: argparse.Namespace) -> int:
    from flows.server import server_env, start_server, stop_unless_used
    from flows.settings import load_settings

    settings = load_settings()
    proc = None
    for key, value in _PREFECT_QUIET.items():
        os.environ.setdefault(key, value)
    if "PREFECT_API_URL" in os.environ:
        if not _api_answers(os.environ["PREFECT_API_URL"]):
            return 2
    else:
        home = settings.prefect_home
        os.environ.update(server_env(home, settings.server_port))
        print(f"starting a local Prefect server on SQLite in {home} ...", flush=True)
        try:
            proc = start_server(home, settings.server_port)
        except RuntimeError as exc:
            print(f"mateqa nightly: {exc}", file=sys.stderr)
            return 1
        print(_server_lines(proc, left_running=not args.stop_server), flush=True)
    try:
        return _run_nightly(args)
    finally:
        if args.stop_server:
            _drain_run_logs()
        busy = stop_unless_used(proc) if args.stop_server else None
        if busy:  # another night's runs: stopping the server would fail them
            port = settings.server_port
            print(f"mateqa nightly: left the Prefect server on port {port} running: {busy}; "
                  f"`mateqa serve --stop{'' if port == 4200 else f' --port {port}'}` stops it "
                  "once they end", file=sys.stderr)


def _drain_run_logs() -> None:
    """Send the log lines still queued for the server before it stops: otherwise Prefect's log
    worker finds it gone at exit and prints "Error logging to API" under the verdict."""
    from prefect.logging.handlers import APILogWorker

    try:
        APILogWorker.drain_all(timeout=5)
    except Exception:  # the night is over; its logs are on disk
        pass


def _api_answers(url: str) -> bool:
    """Whether a Prefect API answers at the ``PREFECT_API_URL`` given; a line when not (the
    night would otherwise fail at its first call, with a page of traceback)."""
    from flows.server import api_problem

    problem = api_problem(url)
    if problem:
        print(f"mateqa nightly: no Prefect API answers at {url} (PREFECT_API_URL): {problem}; "
              "start one (`mateqa serve`), or unset PREFECT_API_URL for a local server the "
              "night starts itself", file=sys.stderr)
    return problem is None


def _server_lines(server: LocalServer, left_running: bool) -> str:
    """What a night says of its local Prefect server: where its UI is, and how to stop it."""
    where = (f"Prefect UI at {server.ui_url}" if server.ui_url
             else f"Prefect API at {server.api_url} (this server has no UI)")
    if server.replaced:
        where += f" (replaced the server without a UI, pid {server.replaced})"
    if not left_running:
        return where
    return (f"{where}; it stays up for later nights: `mateqa serve --stop"
            f"{'' if server.port == 4200 else f' --port {server.port}'}` stops it")


def cmd_serve(args: argparse.Namespace) -> int:
    import signal
    import threading

    from flows.server import (
        api_url,
        apply_deployments,
        project_root,
        server_env,
        start_server,
        start_worker,
        stop_owned,
        stop_process,
    )

    root, home = project_root(), args.home.resolve()
    if args.stop:
        return _stop_serve(args.port, home)
    env = server_env(home, args.port, ui=True)
    env.update({k: env.get(k, v) for k, v in _PREFECT_QUIET.items()})
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    server = worker = None
    try:
        print(f"starting a local Prefect server on SQLite in {home} ...", flush=True)
        server = start_server(home, args.port, ui=True)
        apply_deployments(env, root, home / "deploy.log")
        worker = start_worker(env, root, home / "worker.log")
        owned = server.started or server.left_by_mateqa
        print(f"Prefect UI:  {server.ui_url or '(none: this server has no UI)'} "
              f"({_origin(server)})\nPrefect API: {api_url(args.port)}\n"
              f"work pool 'mateqa' with a process worker (log: {home / 'worker.log'})\n"
              f"deployments of {root / 'prefect.yaml'} applied; run the nightly with\n"
              f"  PREFECT_API_URL={api_url(args.port)} prefect deployment run 'nightly/nightly'"
              f" --param 'config={{\"library\": {{\"path\": \"DIR\"}}}}' --watch\n"
              "Ctrl-C stops the worker and "
              + ("the server." if owned else "leaves the server, which was running before."),
              flush=True)
        while not stop.wait(1.0):
            if worker.poll() is not None:
                print(f"mateqa serve: the worker stopped (exit {worker.returncode}); see "
                      f"{home / 'worker.log'}", file=sys.stderr)
                return 1
        return 0
    except RuntimeError as exc:
        print(f"mateqa serve: {exc}", file=sys.stderr)
        return 1
    finally:
        stop_process(worker)
        if server is not None:
            stop_owned(server)
        print("mateqa serve: stopped", flush=True)



def _origin(server: LocalServer) -> str:
    if server.replaced:
        return f"started in place of a server without a UI, pid {server.replaced}"
    if server.started:
        return "started"
    return "taken over from an earlier night" if server.left_by_mateqa else "already running"


def _stop_serve(port: int, home: Path) -> int:
    from flows.server import stop_port

    try:
        pid = stop_port(port, home)
    except RuntimeError as exc:
        print(f"mateqa serve --stop: {exc}", file=sys.stderr)
        return 1
    print(f"stopped the Prefect server on port {port} (pid {pid})" if pid
          else f"no Prefect server on port {port}")
    return 0


def _run_nightly(args: argparse.Namespace) -> int:
    from cadio.errors import MachineError
    from cadio.workspace_claim import WorkspaceBusyError
    from flows.config import ConfigError
    from flows.nightly import ThresholdFailure, nightly

    state = nightly(config=args.config, return_state=True)
    if not state.is_completed():
        failure = state.result(raise_on_failure=False)
        if isinstance(failure, ThresholdFailure):
            _print_verdict(Path(failure.run_dir), args.json)
            print(f"mateqa nightly: {failure}", file=sys.stderr)
            return 3
        if isinstance(failure, (ConfigError, WorkspaceBusyError)):  # inputs read, or a busy ws
            print(f"mateqa nightly: {failure}", file=sys.stderr)
            return 2
        if isinstance(failure, MachineError):  # the run failed, for a reason it names
            print(f"mateqa nightly: {state.message}", file=sys.stderr)
            return 1
        print(f"mateqa nightly: the run failed: {state.message}", file=sys.stderr)
        return 1
    _print_verdict(Path(state.result().run_dir), args.json)
    return 0


def _print_verdict(run_dir: Path, as_json: bool) -> None:
    from reports.verdict import console_verdict

    print((run_dir / "summary.json").read_text() if as_json else console_verdict(run_dir))
