"""``mateqa nightly`` (the nightly flow, against a Prefect server) and ``mateqa serve`` (a
local server, work pool, worker and the deployments)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# Prefect configures its own loggers when imported; this override (a default the user's
# environment may replace) keeps one "Finished in state Completed()" per task off the console:
# the flow logs one line per stage instead.
_PREFECT_QUIET = {"PREFECT_LOGGING_LOGGERS_PREFECT_TASK_RUNS_LEVEL": "WARNING"}


def cmd_nightly(args: argparse.Namespace) -> int:
    from flows.server import server_env, start_server, stop_server
    from flows.settings import load_settings

    settings = load_settings()
    proc = None
    for key, value in _PREFECT_QUIET.items():
        os.environ.setdefault(key, value)
    if "PREFECT_API_URL" not in os.environ:
        home = settings.prefect_home
        os.environ.update(server_env(home, settings.server_port))
        print(f"starting a local Prefect server on SQLite in {home} ...", flush=True)
        proc = start_server(home, settings.server_port)
        print(f"Prefect API at {os.environ['PREFECT_API_URL']}", flush=True)
    try:
        return _run_nightly(args)
    finally:
        if args.stop_server:
            stop_server(proc)


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
        stop_process,
    )

    root, home = project_root(), args.home.resolve()
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
        print(f"Prefect UI:  http://127.0.0.1:{args.port}\nPrefect API: {api_url(args.port)}\n"
              f"work pool 'mateqa' with a process worker (log: {home / 'worker.log'})\n"
              f"deployments of {root / 'prefect.yaml'} applied; run the nightly with\n"
              f"  PREFECT_API_URL={api_url(args.port)} prefect deployment run 'nightly/nightly'"
              " --param 'config={\"library\": {\"path\": \"DIR\"}}' --watch\n"
              "Ctrl-C stops the worker and the server.",
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
        stop_process(server)
        print("mateqa serve: stopped", flush=True)



def _run_nightly(args: argparse.Namespace) -> int:
    from flows.nightly import ThresholdFailure, nightly

    state = nightly(config=args.config, return_state=True)
    if not state.is_completed():
        failure = state.result(raise_on_failure=False)
        if isinstance(failure, ThresholdFailure):
            _print_verdict(Path(failure.run_dir), args.json)
            print(f"mateqa nightly: {failure}", file=sys.stderr)
            return 3
        print(f"mateqa nightly: the run failed: {state.message}", file=sys.stderr)
        return 1
    _print_verdict(Path(state.result().run_dir), args.json)
    return 0


def _print_verdict(run_dir: Path, as_json: bool) -> None:
    from reports.verdict import console_verdict

    print((run_dir / "summary.json").read_text() if as_json else console_verdict(run_dir))
