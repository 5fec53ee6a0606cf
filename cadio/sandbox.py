"""Run CAD work in separate worker processes with a time limit and a memory limit.

OpenCascade can hang on a pathological file, exhaust memory, or crash the whole process with a
segmentation fault. None of that may stop a batch: each job runs in a long-lived worker process
(never a fork of its supervisor, so OCP state is not shared) with an address-space limit; the
supervisor waits on results and worker deaths together, turns a timeout, a memory error or a
crash into a ``WorkerError`` naming the input, replaces the dead worker and carries on with the
next job.

Workers are plain subprocesses (``subprocess.Popen`` of this interpreter, or forks of one that
``cadio.forkserver`` started so), not ``multiprocessing`` children: the supervisor may itself
be a daemonic process, as every ``dask worker`` process is, and ``multiprocessing`` refuses
children to those. The job function (by its qualified name) and payload of each job, and its
result, travel as pickles over a socket pair that only the worker inherits; the worker's end
closing is how the supervisor sees it die.

A fresh worker costs 3-6 s of CPU before its first job (OCP, open3d, torch and the job's
module), so workers are forked from a process that loaded those once (``cadio.forkserver``)
where their memory limit allows. A night runs pool after pool (ingest batches, mates, captures,
completion, relations, inspection, export), so a pool that ran its jobs to the end leaves its
live, idle workers to the next pool of this process started in the same context (umask, working
folder, import path and environment, its libraries' threads included: what a worker takes from
its supervisor when it starts). The memory limit is a job's, not a worker's: it is sent with
each job, and a kept worker serves a pool of its limit or a larger one, or of a smaller one
where it maps at most half of that now (lowering a limit under what an earlier job left mapped
would fail the next job's allocations), so that the stages' pools of different limits share
their workers. A kept worker leaves by itself after ``KEEP_IDLE_S`` without a job or when this
process ends (its socket closes); ``release_idle_workers`` stops the kept ones at once. A pool
closed early (its caller stopped iterating) keeps nothing.
"""

from __future__ import annotations

import logging
import os
import resource
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any, Generic, TypeVar

from cadio.errors import CadioError, InputFileError, MachineError, WorkerError
from cadio.forkserver import Forked, fork_server, mapped_mb

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Limits:
    """Resource limits of one worker process.

    seconds: wall-clock limit per job (a 10 MB STEP reads in seconds; minutes mean a hang).
    memory_mb: address-space limit; OCP + open3d + numpy map ~1.5 GB of address space at idle,
    so limits under ~2 GB make every job fail.
    workers: processes running jobs at once.
    threads: kernel threads per worker (below).
    """

    seconds: float = 300.0
    memory_mb: int = 6144
    workers: int = 2
    # Threads of a worker's numerical libraries (OpenMP, BLAS; open3d's ray casting); None:
    # as this process has them. Two workers on two cores with a pool of threads each ran an
    # inspection 1.3x slower than with one thread each.
    threads: int | None = None


P = TypeVar("P")  # a job's payload: a typed record of the stage (e.g. ``IngestJob``)
R = TypeVar("R")  # what the job function returns for it


@dataclass(frozen=True)
class Job(Generic[P]):
    """One unit of work: ``key`` names the input (a file path) in errors."""

    key: str
    payload: P


@dataclass(frozen=True)
class Outcome(Generic[P, R]):
    """The result of a job, or the error that ended it (then ``result`` is None)."""

    job: Job[P]
    result: R | None = None
    error: InputFileError | None = None
    seconds: float = 0.0


def run_isolated(
    fn: Callable[[P], R], jobs: Iterable[Job[P]], limits: Limits = Limits()
) -> Iterator[Outcome[P, R]]:
    """Run ``fn(payload)`` for every job in isolated worker processes.

    Args:
        fn: a module-level function of an importable module (not ``__main__``: it travels
            to the workers by its qualified name); it takes a job payload and returns a
            picklable result, and raises ``InputFileError`` for bad input.
        jobs: the jobs; their order of completion may differ.
        limits: time, memory and parallelism limits.

    Yields:
        One ``Outcome`` per job, as jobs finish.

    Raises:
        MachineError: a job met a fault of the machine (``fn`` raised it: a full disk, a
            workspace it cannot write); the other jobs are stopped, since none would fare
            better, and no job's outcome stands for an input that failed.
        ValueError: ``fn`` is defined in ``__main__`` or is no module-level function.
    """
    name = f"{getattr(fn, '__module__', '__main__')}.{getattr(fn, '__qualname__', '')}"
    if name.startswith("__main__.") or "<" in name:
        raise ValueError(f"{fn!r}: the job must be a module-level function of an importable "
                         "module (workers import it by name)")
    pool: _Pool[P, R] = _Pool(fn, limits)
    try:
        yield from pool.run(deque(jobs))
    finally:
        pool.close()


# Seconds an idle kept worker waits for its next job before it leaves; a pool takes a kept
# worker only while it has at least ``_TAKE_MARGIN_S`` of that left.
KEEP_IDLE_S = 60.0
_TAKE_MARGIN_S = 15.0


# What a worker runs first: take the supervisor's import path from the socket before
# importing anything of this package (the job's module may live on that path only).
_BOOT = ("import sys\n"
         "from multiprocessing.connection import Connection\n"
         "conn = Connection(int(sys.argv[1]))\n"
         "sys.path[:] = conn.recv()\n"
         "from cadio.sandbox import _worker_main\n"
         "_worker_main(conn, int(sys.argv[2]))\n")


# Worker processes started and not yet reaped, in every pool of this process.
_LIVE: set[subprocess.Popen[bytes] | Forked] = set()
# Held while a worker starts and is registered, and while ``kill_workers`` reads the set: a
# worker whose interpreter has started is never missed by a kill (a pool in another thread
# could otherwise be between the two).
_STARTING = threading.Lock()
# Idle workers kept for the next pool, by context (``_context``), oldest first (``_Pool.close``).
_IDLE: dict[tuple[object, ...], list[_Worker[Any]]] = {}
_IDLE_LOCK = threading.Lock()


def release_idle_workers() -> int:
    """Stop the idle workers kept for later pools now; returns how many there were."""
    with _IDLE_LOCK:
        kept = [w for workers in _IDLE.values() for w in workers]
        _IDLE.clear()
    _stop(kept)
    return len(kept)


def _context(threads: int | None = None) -> tuple[object, ...]:
    """What a worker inherits from this process when it starts (its environment as
    ``threads`` sets it): a kept worker serves a later pool only where all of it is still the
    same. Pools that ask for no threads and for as many as this process's environment already
    sets share their workers."""
    environment = _environment(threads) or os.environ
    return (_umask(), os.getcwd(), tuple(sys.path), tuple(sorted(environment.items())))


THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _environment(threads: int | None) -> dict[str, str] | None:
    """A worker's environment: this process's, its numerical libraries held to ``threads``."""
    if threads is None:
        return None
    return {**os.environ, **{name: str(threads) for name in THREAD_VARIABLES}}


def _umask() -> int:
    """This process's umask, read without setting it (Linux), else set and restored."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _take_idle(context: tuple[object, ...], memory_mb: int) -> _Worker[Any] | None:
    """A kept worker of this context that may run under ``memory_mb`` (module docstring),
    alive and not about to leave (the most recently idle first), or None. Those about to leave
    are stopped on the way."""
    with _IDLE_LOCK:
        kept = _IDLE.get(context, [])
        for worker in kept[::-1]:
            fresh = time.monotonic() - worker.idle_since < KEEP_IDLE_S - _TAKE_MARGIN_S
            if not (worker.alive() and fresh):
                kept.remove(worker)
                worker.kill()
            elif worker.memory_mb <= memory_mb or worker.mapped_mb() <= memory_mb / 2:
                kept.remove(worker)
                return worker
    return None


def kill_workers() -> int:
    """Kill every running worker of this process's pools at once, without waiting for their
    jobs (a night that stops on a signal must not wait minutes for a CAD file; the pools see
    the deaths as crashes). Returns how many were running."""
    with _STARTING:
        running = [proc for proc in list(_LIVE) if proc.poll() is None]
        for proc in running:
            proc.kill()
    return len(running)


class _Worker(Generic[P]):
    def __init__(self, memory_mb: int, threads: int | None = None) -> None:
        mine, theirs = socket.socketpair()
        with mine, theirs:
            fd = theirs.fileno()
            environment = _environment(threads)
            inherited = dict(environment or os.environ)
            context = {"cwd": os.getcwd(), "umask": _umask(), "path": list(sys.path),
                       "environment": inherited}
            server = fork_server(inherited, THREAD_VARIABLES)
            with _STARTING:
                # forked from the fork server where it can (``cadio.forkserver``), else
                # started fresh; stdout to /dev/null: OpenCascade prints parser chatter
                # straight to fd 1
                forked = server.fork(fd, memory_mb, context) if server else None
                self.process: subprocess.Popen[bytes] | Forked = forked or subprocess.Popen(
                    [sys.executable, "-c", _BOOT, str(fd), str(memory_mb)], pass_fds=(fd,),
                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, env=environment)
                _LIVE.add(self.process)
            self.conn = Connection(mine.detach())
        if isinstance(self.process, subprocess.Popen):
            self.send(list(sys.path))
        self.memory_mb = memory_mb  # the limit of its last job (it sets each job's)
        self.job: Job[P] | None = None
        self.started = self.idle_since = 0.0

    def send(self, value: Any) -> None:
        try:
            self.conn.send(value)
        except OSError:
            pass  # it died already: its closed socket shows that to the supervisor

    def alive(self) -> bool:
        return self.process.poll() is None

    def mapped_mb(self) -> float:
        """Its address space now, MB (what a memory limit holds); infinite where unknown."""
        return mapped_mb(self.process.pid)

    def submit(self, fn: Callable[[P], Any], job: Job[P], memory_mb: int) -> None:
        self.job, self.started, self.memory_mb = job, time.monotonic(), memory_mb
        self.send((fn, job.payload, memory_mb))

    def kill(self) -> None:
        if self.alive():
            self.process.kill()
        self.reap(5)
        self.conn.close()

    def reap(self, seconds: float) -> None:
        try:
            self.process.wait(seconds)
        except subprocess.TimeoutExpired:
            log.warning("worker %d did not exit within %g s", self.process.pid, seconds)
            return
        _LIVE.discard(self.process)


class _Pool(Generic[P, R]):
    def __init__(self, fn: Callable[[P], R], limits: Limits) -> None:
        self.fn, self.limits = fn, limits
        self.workers: list[_Worker[P]] = []
        self.queue: deque[Job[P]] = deque()
        self.context = _context(limits.threads)

    def run(self, queue: deque[Job[P]]) -> Iterator[Outcome[P, R]]:
        self.queue = queue
        while queue or any(w.job for w in self.workers):
            self._fill(queue)
            busy = [w for w in self.workers if w.job is not None]
            ready = wait([w.conn for w in busy], timeout=self._next_deadline(busy))
            for worker in busy:
                outcome = self._check(worker, ready)
                if outcome is not None:
                    yield outcome

    def _fill(self, queue: deque[Job[P]]) -> None:
        for worker in [w for w in self.workers if w.job is None and not w.alive()]:
            worker.kill()  # died between jobs: reap it and close its socket
            self.workers.remove(worker)
        while len(self.workers) < min(self.limits.workers, len(queue) + self._busy()):
            kept = _take_idle(self.context, self.limits.memory_mb)
            self.workers.append(kept or _Worker(self.limits.memory_mb, self.limits.threads))
        for worker in self.workers:
            if worker.job is None and queue:
                worker.submit(self.fn, queue.popleft(), self.limits.memory_mb)

    def _busy(self) -> int:
        return sum(w.job is not None for w in self.workers)

    def _next_deadline(self, busy: list[_Worker[P]]) -> float:
        now = time.monotonic()
        return max(0.0, min(w.started + self.limits.seconds - now for w in busy))

    def _check(self, worker: _Worker[P], ready: list[Any]) -> Outcome[P, R] | None:
        job = worker.job
        assert job is not None
        elapsed = time.monotonic() - worker.started
        if worker.conn in ready:
            try:
                status, value = worker.conn.recv()
            except (EOFError, OSError):
                status, value = "died", None
            if status != "died":
                worker.job = None
                if status == "ok":
                    return Outcome(job, result=value, seconds=elapsed)
                if status == "machine":
                    raise value
                return Outcome(job, error=_rebuild_error(job.key, value), seconds=elapsed)
        if worker.conn in ready or not worker.alive():  # its socket closed: it died
            worker.reap(5)
            if worker.process.returncode == 0:  # a kept worker that left idle as it was sent
                worker.kill()  # the job: no crash, the job goes to another worker
                self.workers.remove(worker)
                self.queue.appendleft(job)
                return None
            reason = _death_reason(worker.process.returncode, self.limits)
            return self._retire(worker, reason, elapsed)
        if elapsed >= self.limits.seconds:
            reason = f"timed out after {self.limits.seconds:g} s (worker killed)"
            return self._retire(worker, reason, elapsed)
        return None

    def _retire(self, worker: _Worker[P], reason: str, elapsed: float) -> Outcome[P, R]:
        job = worker.job
        assert job is not None
        worker.kill()
        self.workers.remove(worker)
        log.warning("%r: %s", job.key, reason)  # the key names an input: quoted, one line
        return Outcome(job, error=WorkerError(job.key, reason), seconds=elapsed)

    def close(self) -> None:
        idle = [w for w in self.workers if w.job is None and w.alive()]
        if not self.queue and len(idle) == len(self.workers):  # ran to the end: keep them
            now = time.monotonic()
            with _IDLE_LOCK:
                kept = _IDLE.setdefault(self.context, [])
                for worker in idle:
                    worker.idle_since = now
                kept.extend(idle)
                # one pool's worth, or a worker a core: pools of one worker each run side by
                # side (the completion's and the relations' batches, two tasks at once)
                room = max(self.limits.workers, os.cpu_count() or 1)
                surplus = kept[:max(0, len(kept) - room)]
                del kept[:len(surplus)]
            self.workers = idle = surplus  # beyond one pool's worth: stopped below
        _stop(idle)
        for worker in self.workers:
            worker.kill()
        self.workers = []


def _stop(idle: list[_Worker[Any]]) -> None:
    """Ask idle workers to leave, all told first so that they wind down side by side; kill
    those that did not within 2 s."""
    for worker in idle:
        worker.send(None)
    for worker in idle:
        try:
            worker.process.wait(2)
        except subprocess.TimeoutExpired:
            pass
        worker.kill()


def _death_reason(exitcode: int | None, limits: Limits) -> str:
    if exitcode is not None and exitcode < 0:
        name = signal.Signals(-exitcode).name
        if -exitcode == signal.SIGKILL:
            return f"worker killed ({name}), likely by the system's out-of-memory killer"
        if -exitcode == signal.SIGABRT:
            return f"worker aborted ({name}); often an allocation beyond {limits.memory_mb} MB"
        return f"the reader crashed inside the CAD kernel ({name})"
    return f"worker exited unexpectedly with code {exitcode}"


def _rebuild_error(key: str, value: tuple[str, str]) -> InputFileError:
    kind, reason = value
    if kind == "memory":
        return WorkerError(key, reason)
    return InputFileError(key, reason)


def _worker_main(conn: Connection, memory_mb: int) -> None:
    """Entry point of a worker (after ``_BOOT``): limit memory, serve (function, payload,
    memory limit) jobs until told to stop, the supervisor's end closes or no job came for
    ``KEEP_IDLE_S``.

    The worker leaves with ``os._exit``: every result is sent by then, and tearing down an
    interpreter that holds OCP and open3d costs about half a second of CPU (exit handlers do
    not run in workers, so nothing may rely on them there).
    """
    _limit_memory(memory_mb)
    try:
        while conn.poll(KEEP_IDLE_S) and (job := conn.recv()) is not None:
            fn, payload, memory_mb = job
            _limit_memory(memory_mb)
            conn.send(_serve(fn, payload, memory_mb))
    except (EOFError, OSError):
        pass  # the supervisor is gone or gave up on this worker
    logging.shutdown()
    sys.stderr.flush()
    os._exit(0)


def _serve(fn: Callable[[Any], Any], payload: Any, memory_mb: int) -> tuple[str, Any]:
    try:
        return "ok", fn(payload)
    except MemoryError:
        return "error", ("memory", f"memory limit of {memory_mb} MB exceeded")
    except MachineError as exc:  # the machine's, not the input's: the supervisor raises it
        return "machine", exc
    except InputFileError as exc:
        return "error", ("input", exc.reason)
    except CadioError as exc:
        return "error", ("input", str(exc))
    except Exception as exc:  # a kernel failure on this input must not end the worker
        return "error", ("input", f"{type(exc).__name__}: {exc}")


def _limit_memory(memory_mb: int) -> None:
    """Hold this process's address space to ``memory_mb`` (the soft limit: a later job of a
    larger limit raises it, up to the hard limit it inherited)."""
    limit = memory_mb * 1024 * 1024
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
