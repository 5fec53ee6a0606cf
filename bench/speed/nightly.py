"""Benchmark of the nightly: wall time per stage, peak memory, and Prefect's share.

The same stages run twice on fresh workspaces, each in its own process:
- ``flow``: the ``nightly`` Prefect flow against a local Prefect server on SQLite (started here);
- ``direct``: the very same stage code (``flows.nightly.stages_of``) with every task called as
  a plain function on a two-thread pool, as the flow's task runner does, and no Prefect at all.
Prefect's share is flow / direct wall time (goal: at most 1.05). A third run repeats the flow
on the flow's workspace: the unchanged library must only be reported (the cache at work).
Peak memory is the largest resident set of the run's process and of its CAD worker processes.

Usage: ``.venv/bin/python bench/speed/nightly.py [--library DIR] [--views 8] [--pairs 4]``
(default library: the built-in sample library; about 25 minutes on two cores).

Scaling (``--scale 1 3 10 [--categories C ...]``): the library (the chosen categories of it)
copied k times, each copy with new bytes and a new file name so that every copy is new work,
and the scenes per relation multiplied by k, so k x the library is k x the work; each size runs
through the flow on this machine's thread pool and on a Dask cluster (a scheduler and two
workers on loopback, started here for each run) on fresh workspaces. Reported: wall time, time
per unit of work against 1x (goal: 10x the work in at most 10.5x the time) and peak memory
(the flow's process, its CAD workers, and each Dask worker).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
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
    from flows.config import night_config

    return nightly_module.stages_of(night_config(params)).stage_seconds


def run_flow(params: dict[str, Any]) -> dict[str, Any]:
    from flows.config import night_config
    from flows.nightly import nightly

    summary = nightly(night_config(params))
    return {**summary.stage_seconds, "parts": summary.ingest.parts}


def merged(config: dict[str, Any], **groups: dict[str, Any]) -> dict[str, Any]:
    """A night's configuration (nested, as ``NightConfig`` takes it) with groups updated."""
    out = {name: dict(values) for name, values in config.items()}
    for name, values in groups.items():
        out.setdefault(name, {}).update(values)
    return out


def child(mode: str, params: dict[str, Any]) -> None:
    """One measured run in this process; prints a JSON line."""
    logging.basicConfig(level=logging.WARNING)
    start = time.perf_counter()
    stages = (run_flow if mode == "flow" else run_direct)(params)
    parts = stages.pop("parts", None)
    used = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    print(json.dumps({
        "mode": mode, "wall_s": round(time.perf_counter() - start, 1), "stages": stages,
        "parts": parts, "cpu_s": round(sum(u.ru_utime + u.ru_stime for u in used), 1),
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


_FILE_NAME = re.compile(rb"(FILE_NAME\s*\(\s*)'[^']*'")


def scaled_library(base: Path, k: int, out: Path, categories: list[str] | None) -> Path:
    """k copies of every STEP file under ``base`` (of ``categories`` only, when given), in the
    same category folders, copy i named ``<stem>__c<i>`` with that name in its header."""
    for path in sorted(base.rglob("*.st*p")):
        category = path.relative_to(base).parts[0]
        if categories and category not in categories:
            continue
        data = path.read_bytes()
        for i in range(k):
            name = f"{path.stem}__c{i}"
            target = out / category / f"{name}{path.suffix}"
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(_FILE_NAME.sub(lambda m, n=name: m.group(1) + f"'{n}'".encode(),
                                              data, count=1))
    return out


@contextlib.contextmanager
def dask_cluster(log: Path, workers: int = 2) -> Iterator[str]:
    """A Dask scheduler and ``workers`` one-thread workers on loopback; yields the address."""
    from distributed import Client

    port = 8790
    address = f"tcp://127.0.0.1:{port}"
    dask = str(Path(sys.executable).with_name("dask"))
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False", "OMP_NUM_THREADS": "1"}
    with log.open("ab") as out:
        procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port",
                                   str(port), "--no-dashboard"], stdout=out,
                                  stderr=subprocess.STDOUT)]
        procs += [subprocess.Popen([dask, "worker", address, "--nthreads", "1",
                                    "--no-dashboard", "--name", f"w{i}"], cwd=ROOT, env=env,
                                   stdout=out, stderr=subprocess.STDOUT)
                  for i in range(workers)]
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                with Client(address, timeout=5) as client:
                    if len(client.scheduler_info()["workers"]) == workers:
                        break
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise SystemExit(f"the Dask cluster did not start: {log}")
            time.sleep(1)
        yield address
    finally:
        for proc in procs[::-1]:
            proc.terminate()
            proc.wait(60)


def _dask_peak_mb(address: str) -> int:
    """The largest peak resident set of the cluster's worker processes and their children."""
    from distributed import Client

    def peak() -> int:
        own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        return int(max(own, kids) / 1024)

    with Client(address, timeout=10) as client:
        return max(client.run(peak).values())


def scaling(args: argparse.Namespace, root: Path, base: dict[str, Any],
            env: dict[str, str]) -> None:
    """The flow on k x the library, local and on Dask; a table."""
    from cadio.samples.library import generate_library

    source = args.library.resolve() if args.library else root / "samples"
    if not args.library:
        generate_library(source)
    rows = []
    for k in args.scale:
        library = scaled_library(source, k, root / f"library-x{k}", args.categories)
        params = merged(base, library={"path": str(library), "categories": None},
                        capture={"pairs_per_relation": args.pairs * k})
        for runner in args.runners:
            ws = root / f"ws-{runner}-x{k}"
            if runner == "dask":
                with dask_cluster(root / "dask.log") as address:
                    run = measure("flow", merged(params, runtime={
                        "workspace": str(ws), "dask_address": address}), env)
                    run["peak_dask_worker_mb"] = _dask_peak_mb(address)
            else:
                run = measure("flow", merged(params, runtime={
                    "workspace": str(ws), "dask_address": ""}), env)
            run.update(scale=k, runner=runner)
            rows.append(run)
            print(json.dumps(run), flush=True)
    print(f"library: {args.library or 'built-in samples'} "
          f"({', '.join(args.categories or ['all categories'])}); views {args.views}, "
          f"pairs/relation {args.pairs} x k")
    print(f"{'runner':<8}{'k':>4}{'parts':>7}{'wall s':>9}{'s/part':>8}{'CPU s':>8}{'x 1x':>8}"
          f"{'/ k':>7}{'peak MB':>9}{'CAD MB':>8}{'Dask MB':>9}")
    for r in rows:
        one = next(x for x in rows if x["runner"] == r["runner"] and x["scale"] == args.scale[0])
        ratio = r["wall_s"] / one["wall_s"]
        per_part = r["wall_s"] / r["parts"] if r.get("parts") else float("nan")
        print(f"{r['runner']:<8}{r['scale']:>4}{r.get('parts') or '-':>7}{r['wall_s']:>9.1f}"
              f"{per_part:>8.2f}{r.get('cpu_s', float('nan')):>8.1f}{ratio:>8.2f}"
              f"{ratio / (r['scale'] / args.scale[0]):>7.2f}{r['peak_rss_mb']:>9}"
              f"{r['peak_worker_rss_mb']:>8}{r.get('peak_dask_worker_mb', '-'):>9}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--library", type=Path, default=None)
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--pairs", type=int, default=4)
    parser.add_argument("--scale", type=int, nargs="+", default=None,
                        help="library multiples to time (e.g. 1 3 10): the scaling run")
    parser.add_argument("--categories", nargs="+", default=None,
                        help="scaling: only these categories of the library")
    parser.add_argument("--runners", nargs="+", default=["local", "dask"],
                        choices=["local", "dask"], help="scaling: the task runners to time")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--params", default="{}", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child, json.loads(args.params))
        return
    from flows.server import server_env, start_server, stop_server

    root = Path(tempfile.mkdtemp(prefix="bench-nightly-"))
    env = {**server_env(root / "prefect", 4250), "OMP_NUM_THREADS": "1",
           "PREFECT_LOGGING_LEVEL": "WARNING"}
    os.environ.update(env)
    server = start_server(root / "prefect", 4250)
    base = {"library": {"path": str(args.library.resolve()) if args.library else None},
            "capture": {"views_per_scene": args.views, "pairs_per_relation": args.pairs},
            "thresholds": {"fail_on_threshold": False}}
    if args.scale:
        try:
            scaling(args, root, base, env)
        finally:
            stop_server(server)
        return
    try:
        flow = measure("flow", merged(base, runtime={"workspace": str(root / "flow")}), env)
        direct = measure("direct", merged(base, runtime={"workspace": str(root / "direct")}),
                         env)
        again = measure("flow", merged(base, runtime={"workspace": str(root / "flow")}), env)
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
