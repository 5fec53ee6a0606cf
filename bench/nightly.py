"""Benchmark of the nightly: wall time per stage, peak memory, and Prefect's share.

The same stages run twice on fresh workspaces, each in its own process:
- ``flow``: the ``nightly`` Prefect flow against a local Prefect server on SQLite (started here);
- ``direct``: the very same stage code (``flows.nightly.run_stages``) with every task called as
  a plain function on a two-thread pool, as the flow's task runner does, and no Prefect at all.
Prefect's share is flow / direct wall time (goal: at most 1.05). A third run repeats the flow
on the flow's workspace: the unchanged library must only be reported (the cache at work).
Peak memory is the largest resident set of the run's process and of its CAD worker processes.

Usage: ``.venv/bin/python bench/nightly.py [--library DIR] [--views 8] [--pairs 4]``
(default library: the built-in sample library; about 25 minutes on two cores).
"""

from __future__ import annotations

import argparse
import inspect
import json
import logging
import os
import resource
import subprocess
import sys
import tempfile
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from anywhere


class Direct:
    """A Prefect task called without Prefect: ``submit`` runs its function on a shared pool."""

    def __init__(self, task: Any, pool: ThreadPoolExecutor) -> None:
        self.fn, self.pool = task.fn, pool

    def submit(self, *args: Any, **kwargs: Any) -> Future[Any]:
        return self.pool.submit(self.fn, *args, **kwargs)

    def with_options(self, **_: Any) -> Direct:
        return self

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.fn(*args, **kwargs)


def run_direct(params: dict[str, Any]) -> dict[str, Any]:
    """``run_stages`` with every task of the flows replaced by ``Direct``."""
    from prefect import Task

    import flows.nightly as nightly_module
    import flows.tasks as tasks_module

    pool = ThreadPoolExecutor(max_workers=2)
    for module in (tasks_module, nightly_module):
        for name, value in list(vars(module).items()):
            if isinstance(value, Task):
                setattr(module, name, Direct(value, pool))
    nightly_module.get_run_logger = lambda: logging.getLogger("nightly")  # type: ignore[assignment]
    nightly_module.publish = lambda *a, **k: None  # type: ignore[attr-defined]
    from cadio.tolerances import DEFAULT_TOLERANCES

    stages = nightly_module.run_stages.fn
    wanted = inspect.signature(stages).parameters
    params = {"tolerances": DEFAULT_TOLERANCES, **params}
    summary = stages(**{k: v for k, v in params.items() if k in wanted})
    return summary.stage_seconds


def run_flow(params: dict[str, Any]) -> dict[str, Any]:
    from flows.nightly import nightly

    return nightly(**params).stage_seconds


def child(mode: str, params: dict[str, Any]) -> None:
    """One measured run in this process; prints a JSON line."""
    logging.basicConfig(level=logging.WARNING)
    start = time.perf_counter()
    stages = (run_flow if mode == "flow" else run_direct)(params)
    print(json.dumps({
        "mode": mode, "wall_s": round(time.perf_counter() - start, 1), "stages": stages,
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "peak_worker_rss_mb": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
                                    / 1024)}))


def measure(mode: str, params: dict[str, Any], env: dict[str, str]) -> dict[str, Any]:
    done = subprocess.run([sys.executable, __file__, "--child", mode, "--params",
                           json.dumps(params)], env=env, cwd=ROOT, capture_output=True,
                          text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{mode} run failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--library", type=Path, default=None)
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--pairs", type=int, default=4)
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--params", default="{}", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child, json.loads(args.params))
        return
    from flows.nightly import nightly
    from flows.server import server_env, start_server, stop_server

    root = Path(tempfile.mkdtemp(prefix="bench-nightly-"))
    env = {**server_env(root / "prefect", 4250), "OMP_NUM_THREADS": "1",
           "PREFECT_LOGGING_LEVEL": "WARNING"}
    os.environ.update(env)
    server = start_server(root / "prefect", 4250)
    base = {name: p.default for name, p in inspect.signature(nightly.fn).parameters.items()}
    base.update(library=str(args.library.resolve()) if args.library else None,
                views_per_scene=args.views, pairs_per_relation=args.pairs,
                fail_on_threshold=False)
    base.pop("tolerances")  # the default object; JSON carries plain values only
    try:
        flow = measure("flow", {**base, "workspace": str(root / "flow")}, env)
        direct = measure("direct", {**base, "workspace": str(root / "direct")}, env)
        again = measure("flow", {**base, "workspace": str(root / "flow")}, env)
    finally:
        stop_server(server)
    report(args, flow, direct, again)


def report(args: argparse.Namespace, flow: dict[str, Any], direct: dict[str, Any],
           again: dict[str, Any]) -> None:
    print(f"library: {args.library or 'built-in samples'}; views {args.views}, "
          f"pairs/relation {args.pairs}")
    print(f"{'stage':<12}{'flow s':>10}{'direct s':>10}{'ratio':>8}{'rerun s':>10}")
    for stage, seconds in flow["stages"].items():
        plain = direct["stages"].get(stage, float("nan"))
        ratio = seconds / plain if plain else float("nan")
        print(f"{stage:<12}{seconds:>10.1f}{plain:>10.1f}{ratio:>8.2f}"
              f"{again['stages'].get(stage, float('nan')):>10.1f}")
    print(f"{'total':<12}{flow['wall_s']:>10.1f}{direct['wall_s']:>10.1f}"
          f"{flow['wall_s'] / direct['wall_s']:>8.2f}{again['wall_s']:>10.1f}")
    for run in (flow, direct, again):
        print(f"peak RSS {run['mode']}: {run['peak_rss_mb']} MB (process), "
              f"{run['peak_worker_rss_mb']} MB (largest CAD worker)")


if __name__ == "__main__":
    main()
