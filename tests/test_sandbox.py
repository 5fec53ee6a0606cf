"""The isolated worker pool survives crashes, hangs and memory exhaustion of its jobs."""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from pathlib import Path

import psutil
import pytest
from sandbox_targets import misbehave, run_in_daemon

from cadio.errors import WorkerError
from cadio.sandbox import (
    _IDLE,
    THREAD_VARIABLES,
    Job,
    Limits,
    Outcome,
    kill_workers,
    release_idle_workers,
    run_isolated,
)


def _run(payloads: list[str], limits: Limits) -> dict[str, object]:
    outcomes = run_isolated(misbehave, [Job(p, p) for p in payloads], limits)
    return {o.job.key: (o.error if o.error is not None else o.result) for o in outcomes}


def test_segfault_becomes_error_and_batch_goes_on() -> None:
    out = _run(["ok:a", "segfault", "ok:b", "ok:c"], Limits(seconds=60, workers=1))
    assert out["ok:a"] == "a" and out["ok:b"] == "b" and out["ok:c"] == "c"
    err = out["segfault"]
    assert isinstance(err, WorkerError)
    assert "SIGSEGV" in err.reason and err.path == "segfault"


def test_hang_is_killed_after_the_time_limit() -> None:
    out = _run(["hang", "ok:after"], Limits(seconds=2, workers=1))
    assert isinstance(out["hang"], WorkerError)
    assert "timed out after 2 s" in out["hang"].reason
    assert out["ok:after"] == "after"


def test_memory_limit_is_enforced() -> None:
    out = _run(["memory", "ok:after"], Limits(seconds=60, memory_mb=1024, workers=1))
    err = out["memory"]
    assert isinstance(err, WorkerError)
    assert "memory" in err.reason
    assert out["ok:after"] == "after"


def test_exceptions_are_reported_and_workers_run_in_parallel() -> None:
    payloads = ["raise"] + [f"ok:{i}" for i in range(6)]
    out = _run(payloads, Limits(seconds=60, workers=2))
    assert len(out) == 7
    assert "ValueError: bad payload" in str(out["raise"])
    assert [out[f"ok:{i}"] for i in range(6)] == [str(i) for i in range(6)]


def test_a_fault_of_the_machine_is_raised_never_an_input_error() -> None:
    """A job that meets a full disk ends the batch with that error: no outcome stands for a
    failed input, which would be reported (and kept) as the input's fault."""
    from cadio.errors import MachineError

    with pytest.raises(MachineError, match="No space left on device") as err:
        _run(["ok:a", "full-disk", "ok:b"], Limits(seconds=60, workers=1))
    assert err.value.path.endswith("never-written")
    assert "errno 28" in err.value.reason


def test_the_sandbox_runs_inside_a_daemonic_process() -> None:
    """A ``dask worker`` process is daemonic, and multiprocessing gives such a process no
    children: the sandbox's workers are plain subprocesses, with the same limits there."""
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    payloads = ["ok:a", "segfault", "hang", "memory", "ok:b"]
    proc = ctx.Process(target=run_in_daemon, daemon=True,
                       args=(payloads, Limits(seconds=10, memory_mb=1024, workers=2), out))
    proc.start()
    proc.join(300)
    assert proc.exitcode == 0  # multiprocessing children: "daemonic processes are not ..."
    daemonic, found = out.get(timeout=10)
    assert daemonic
    assert found["ok:a"] == "a" and found["ok:b"] == "b"
    assert "SIGSEGV" in found["segfault"]
    assert "timed out after 10 s" in found["hang"]
    assert "memory" in found["memory"]


def _workers() -> list[psutil.Process]:
    # workers started fresh (children of this process) and forked ones (children of its fork
    # servers, with their command line); a worker that exited and is not reaped yet (a
    # zombie) runs nothing: not counted
    out = []
    for p in psutil.Process().children(recursive=True):
        try:
            forked = "cadio.forkserver" in " ".join(p.parent().cmdline())
            if p.status() != psutil.STATUS_ZOMBIE and (
                    forked or "cadio.sandbox" in " ".join(p.cmdline())):
                out.append(p)
        except psutil.NoSuchProcess:
            continue
    return out


def test_a_pool_run_to_the_end_leaves_its_workers_to_the_next_pool() -> None:
    release_idle_workers()
    (first,) = _run(["pid"], Limits(seconds=60, memory_mb=8192, workers=1)).values()
    assert [p.pid for p in _workers()] == [int(first)]  # kept, idle
    (second,) = _run(["pid"], Limits(seconds=60, memory_mb=8192, workers=1)).values()
    assert second == first  # no new interpreter: the kept worker served the next pool
    # (a worker forked from the fork server maps its libraries: about 2.6 GB)
    (lower,) = _run(["limit"], Limits(seconds=60, memory_mb=6144, workers=1)).values()
    assert lower == f"{first}:6144"  # a lower limit than its last, under half: it serves
    (raised,) = _run(["limit"], Limits(seconds=60, memory_mb=16384, workers=1)).values()
    assert raised == f"{first}:16384"  # a higher one: served, the limit raised for the job
    _run(["hold:4096"], Limits(seconds=60, memory_mb=16384, workers=1))
    (other,) = _run(["limit"], Limits(seconds=60, workers=1)).values()
    new, limit = other.split(":")  # it maps more than half of 6144 MB now: a new worker
    assert new != first and limit == "6144"
    before = os.umask(0o027)  # ... and only workers started in the same context serve
    try:
        (masked,) = _run(["pid"], Limits(seconds=60, workers=1)).values()
    finally:
        os.umask(before)
    assert masked not in (first, new)
    both = _run(["limit", "ok:x"], Limits(seconds=60, workers=2))
    assert both["limit"] == f"{new}:6144"  # the kept worker mapping little; not the other
    alive = len(_workers())
    assert alive >= 3 and release_idle_workers() == alive and _workers() == []


def test_a_forked_worker_starts_where_its_supervisor_is_now(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A worker forked from the fork server, started long before, takes the supervisor's
    folder, umask, import path and environment of its own start, as a fresh one does; its
    libraries are loaded already (it is no fresh interpreter: its parent is the fork
    server)."""
    release_idle_workers()
    _run(["ok:start"], Limits(seconds=60, workers=1))  # the fork server is up
    release_idle_workers()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("SANDBOX_TEST", "set after the fork server started")
    monkeypatch.syspath_prepend(str(tmp_path / "modules"))
    before = os.umask(0o027)
    try:
        (where,) = _run(["where"], Limits(seconds=60, workers=1)).values()
        (worker,) = _workers()
    finally:
        os.umask(before)
    assert where == (f"{tmp_path}|27|{tmp_path / 'modules'}|set after the fork server started")
    assert "cadio.forkserver" in " ".join(worker.parent().cmdline())
    assert {"torch", "OCP", "open3d"} <= _loaded_packages(worker)  # "where" loads none
    release_idle_workers()


def test_workers_start_fresh_where_the_fork_server_died() -> None:
    from cadio import forkserver

    release_idle_workers()
    _run(["ok:start"], Limits(seconds=60, workers=1))  # the fork server is up
    release_idle_workers()
    server = forkserver._SERVERS[tuple(os.environ.get(n, "") for n in THREAD_VARIABLES)]
    assert server is not None
    server.process.kill()
    server.process.wait(10)
    try:
        (pid,) = _run(["pid"], Limits(seconds=60, workers=1)).values()
        assert psutil.Process(int(pid)).parent().pid == os.getpid()  # started fresh
        out = _run(["segfault", "ok:after"], Limits(seconds=60, workers=1))
        assert "SIGSEGV" in out["segfault"].reason and out["ok:after"] == "after"
    finally:
        release_idle_workers()
        forkserver._SERVERS.clear()  # the next pools get a fork server again


def _loaded_packages(process: psutil.Process) -> set[str]:
    """The site-packages folders of the shared libraries ``process`` maps."""
    out = set()
    for m in process.memory_maps():
        if "site-packages/" in m.path:
            out.add(m.path.split("site-packages/", 1)[1].split("/", 1)[0])
    return out


def test_a_worker_holds_its_libraries_to_the_threads_it_is_given(
        monkeypatch: pytest.MonkeyPatch) -> None:
    release_idle_workers()
    for name in THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    one = _run(["env:OMP_NUM_THREADS", "env:OPENBLAS_NUM_THREADS", "pid"],
               Limits(seconds=60, workers=1, threads=1))
    assert one["env:OMP_NUM_THREADS"] == one["env:OPENBLAS_NUM_THREADS"] == "1"
    inherited = _run(["env:OMP_NUM_THREADS", "pid"], Limits(seconds=60, workers=1))
    assert inherited["env:OMP_NUM_THREADS"] == ""
    assert inherited["pid"] != one["pid"]  # a kept worker serves only pools of its threads
    release_idle_workers()
    for name in THREAD_VARIABLES:  # where this process holds them to one thread already,
        monkeypatch.setenv(name, "1")  # pools of no setting and of one thread are alike
    one = _run(["pid"], Limits(seconds=60, workers=1, threads=1))
    assert _run(["pid"], Limits(seconds=60, workers=1)) == one
    release_idle_workers()


def test_a_kept_worker_leaving_as_a_job_is_sent_loses_no_job() -> None:
    release_idle_workers()
    _run(["ok:a"], Limits(seconds=60, workers=1))
    (kept,) = next(iter(_IDLE.values()))
    kept.conn.send(None)  # it leaves with exit code 0, as after KEEP_IDLE_S without a job
    assert kept.process.wait(30) == 0
    kept.alive = lambda: True  # seen alive when taken: the job is sent to a leaver
    out = _run(["ok:b", "ok:c"], Limits(seconds=60, workers=1))
    assert out == {"ok:b": "b", "ok:c": "c"}  # not a crash: both jobs ran on a new worker
    assert all(kept not in workers for workers in _IDLE.values())
    release_idle_workers()


def test_no_worker_outlives_the_batch_even_when_it_is_abandoned() -> None:
    release_idle_workers()
    outcomes = run_isolated(misbehave, [Job(p, p) for p in ["ok:a", "hang", "ok:b"]],
                            Limits(seconds=600, workers=2))
    first = next(outcomes)
    assert first.result == "a" and len(_workers()) == 2
    outcomes.close()  # the caller stops early (an error, a cancelled task): the hang is killed
    assert _workers() == []


def test_kill_workers_ends_running_jobs_at_once() -> None:
    release_idle_workers()
    outcomes = run_isolated(misbehave, [Job("hang", "hang")], Limits(seconds=3600, workers=1))
    done: list[Outcome[str, str]] = []
    batch = threading.Thread(target=lambda: done.extend(outcomes))
    batch.start()
    deadline = time.monotonic() + 300  # a guard against a hang, not a speed check
    while not _workers():
        assert time.monotonic() < deadline, "no worker started"
        time.sleep(0.1)
    assert kill_workers() == 1  # what a night's stop on SIGTERM calls
    batch.join(300)
    assert not batch.is_alive() and _workers() == []
    (outcome,) = done
    assert isinstance(outcome.error, WorkerError) and "SIGKILL" in outcome.error.reason


def test_a_job_must_be_importable_by_name() -> None:
    with pytest.raises(ValueError, match="module-level function"):
        next(run_isolated(lambda p: p, [Job("x", "x")]))
