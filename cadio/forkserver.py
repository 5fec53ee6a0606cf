"""Start sandbox workers by forking a process that has their libraries loaded already.

A sandbox worker is a fresh interpreter, so that no OpenCascade state of its supervisor is
shared; but a fresh interpreter spends 3-6 s of CPU loading OCP, open3d, torch and the job's
module before its first job, and a night, a command or a test run starts dozens of workers.
So each supervisor process starts one *fork server* (per set of thread variables, below): a
fresh interpreter, like a worker, that loads those libraries and the stages' job modules
once, runs no job and holds no CAD state, and forks a worker on request in a few
milliseconds. A forked worker takes the supervisor's working folder, umask, import path and
environment at its start, as a started one does, and then runs the same loop.

What is read when a library loads cannot be changed after the fork: the threads of OpenMP
and BLAS (``THREAD_VARIABLES``). A fork server serves one setting of those; a pool of another
setting gets a fork server of its own.

A forked worker is the fork server's child, not the supervisor's: ``Forked`` gives the
supervisor what it uses of ``subprocess.Popen`` (``pid``, ``poll``, ``wait``, ``kill``,
``returncode``), the exit status read by the fork server, which reaps its children only when
asked (a child's process id is not reused before that, so a kill never reaches another
process). A worker whose memory limit is less than twice what the fork server maps is
started fresh instead: it would begin with the fork server's libraries mapped, which a fresh
worker of a small job does not load. Where the fork server cannot start or has died, workers
are started fresh, as before it.
"""

from __future__ import annotations

import importlib
import logging
import math
import os
import pickle
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from typing import Any

log = logging.getLogger(__name__)

# What a fork server loads before its first fork: the libraries of every stage's jobs and
# the modules of the job functions (each also loads the project's modules it needs).
PRELOAD = ("numpy", "scipy.spatial", "pandas", "OCP.OCP", "open3d", "torch",
           "cadio.cad.ingest", "cadio.truth.assemblies", "cadio.capture.coverage",
           "cadio.inspect.evaluate", "cadio.export.job", "models.evaluate", "models.relate")

# What a fork server runs first: the supervisor's import path from the socket, then the loop.
_BOOT = ("import socket, sys\n"
         "sock = socket.socket(fileno=int(sys.argv[1]))\n"
         "sys.path[:] = __import__('pickle').loads(sock.recv(1 << 20))\n"
         "from cadio.forkserver import _serve_forks\n"
         "_serve_forks(sock)\n")

_MESSAGE = 1 << 20  # the largest request: an environment and an import path
_LOAD_S = 300.0  # a fork server loads in seconds; one that took this long is given up


class Forked:
    """A worker forked by a fork server, with what the pools use of ``subprocess.Popen``."""

    def __init__(self, server: ForkServer, pid: int) -> None:
        self.server, self.pid = server, pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self.server.status(self.pid)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while (code := self.poll()) is None:
            if deadline is not None and time.monotonic() > deadline:
                raise subprocess.TimeoutExpired(f"worker {self.pid}", timeout or 0.0)
            time.sleep(0.01)
        return code

    def kill(self) -> None:
        if self.poll() is None:  # not reaped yet: the process id is still this worker's
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


class ForkServer:
    """One fork server process and the socket to it (requests answered one at a time)."""

    def __init__(self, environment: dict[str, str]) -> None:
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        with theirs:
            self.process = subprocess.Popen(
                [sys.executable, "-c", _BOOT, str(theirs.fileno())],
                pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL, env=environment)
        self.sock, self.lock, self.gone = mine, threading.Lock(), False
        self.sock.sendall(pickle.dumps(list(sys.path)))
        self.sock.settimeout(_LOAD_S)  # a fork server that hangs while loading is given up
        try:
            self.mapped_mb: float = self._reply()  # it answers once loaded
        except OSError:
            self.process.kill()
            self.sock.close()
            raise
        self.sock.settimeout(None)

    def _reply(self) -> Any:
        data = self.sock.recv(_MESSAGE)
        if not data:
            raise OSError("the fork server exited")
        return pickle.loads(data)

    def fork(self, fd: int, memory_mb: int, context: dict[str, Any]) -> Forked | None:
        """A worker serving the socket ``fd`` (it is sent over, this process keeps its own),
        or None where it should start fresh: its memory limit is under twice what this fork
        server maps, or this one has died. ``context``: what the worker takes at its start
        (``cwd``, ``umask``, import ``path``, ``environment``)."""
        if self.gone or memory_mb < 2 * self.mapped_mb:
            return None
        try:
            with self.lock:
                socket.send_fds(self.sock, [pickle.dumps(("fork", memory_mb, context))], [fd])
                return Forked(self, self._reply())
        except OSError as exc:
            log.warning("the fork server is gone (%s): workers start fresh", exc)
            self.gone = True
            self.sock.close()
            return None

    def status(self, pid: int) -> int | None:
        """The worker's exit status (negative: the signal that ended it), None while it runs.
        Where the fork server is gone (its children went to another parent), a worker that
        no longer exists counts as killed."""
        try:
            with self.lock:
                self.sock.sendall(pickle.dumps(("status", pid)))
                return self._reply()  # type: ignore[no-any-return]
        except OSError:
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return -signal.SIGKILL
            return None


# The fork servers of this process, by the thread variables they loaded their libraries with;
# a process forked from this one (its pid differs) starts its own.
_SERVERS: dict[tuple[str, ...], ForkServer | None] = {}
_SERVERS_LOCK = threading.Lock()
_SERVERS_PID = os.getpid()


def fork_server(environment: dict[str, str],
                thread_variables: tuple[str, ...]) -> ForkServer | None:
    """This process's fork server for the ``thread_variables`` of ``environment``, started
    now if none is (it takes seconds to load: call it before taking a lock); None where none
    can start or the last one died (workers then start fresh)."""
    global _SERVERS_PID
    key = tuple(environment.get(name, "") for name in thread_variables)
    with _SERVERS_LOCK:
        if _SERVERS_PID != os.getpid():
            _SERVERS.clear()
            _SERVERS_PID = os.getpid()
        if key not in _SERVERS:
            try:
                _SERVERS[key] = ForkServer(environment)
            except OSError as exc:
                log.warning("no fork server (%s): workers start fresh", exc)
                _SERVERS[key] = None
        server = _SERVERS[key]
        if server is not None and server.gone:
            _SERVERS[key] = server = None
        return server


def _load_numba_target() -> None:
    """numba's CPU target loads its registries where a process first compiles a function or
    loads one from its cache (0.4-0.8 s): here once, so that no forked worker does."""
    try:
        from numba.core.registry import cpu_target

        cpu_target.target_context.refresh()
    except Exception as exc:  # a worker loads it itself, as a fresh one does
        log.warning("fork server: numba's CPU target not loaded (%s)", exc)


def _serve_forks(sock: socket.socket) -> None:
    """The fork server's loop (after ``_BOOT``): load ``PRELOAD``, say how much it maps, then
    fork a worker per request and answer status requests until the supervisor's end closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C is the supervisor's to handle
    for name in PRELOAD:
        try:
            importlib.import_module(name)
        except ImportError as exc:  # a worker that needs it fails as a fresh one would
            log.warning("fork server: %s not loaded (%s)", name, exc)
    _load_numba_target()
    sock.sendall(pickle.dumps(mapped_mb()))
    exited: dict[int, int] = {}
    while True:
        try:
            data, fds, _, _ = socket.recv_fds(sock, _MESSAGE, 1)
        except OSError:
            break
        if not data:
            break
        request = pickle.loads(data)
        if request[0] == "fork":
            _, memory_mb, context = request
            pid = os.fork()
            if pid == 0:
                _become_worker(sock, fds[0], memory_mb, context)
            os.close(fds[0])
            sock.sendall(pickle.dumps(pid))
        else:
            sock.sendall(pickle.dumps(_exit_status(request[1], exited)))
    os._exit(0)


def _exit_status(pid: int, exited: dict[int, int]) -> int | None:
    """A child's exit status (reaped now, or earlier into ``exited``), None while it runs."""
    if pid not in exited:
        try:
            done, status = os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:  # not a child of this process: nothing to say but gone
            done, status = pid, 0
        if done:
            exited[pid] = os.waitstatus_to_exitcode(status)
    return exited.get(pid)


def _become_worker(sock: socket.socket, fd: int, memory_mb: int,
                   context: dict[str, Any]) -> None:
    """In the forked child: take the supervisor's context, as a started worker does, and
    serve jobs; never returns."""
    try:
        sock.close()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            os.chdir(context["cwd"])
        except OSError:
            pass  # a started worker would begin there too: the job says what it lacks
        os.umask(context["umask"])
        os.environ.clear()
        os.environ.update(context["environment"])
        sys.path[:] = context["path"]
        random.seed()  # a fresh interpreter's random state, not the fork server's
        numpy = sys.modules.get("numpy")
        if numpy is not None:
            numpy.random.seed()
        from multiprocessing.connection import Connection

        from cadio.sandbox import _worker_main

        _worker_main(Connection(fd), memory_mb)
    finally:
        os._exit(1)


def mapped_mb(pid: int | str = "self") -> float:
    """A process's address space now, MB (what a memory limit holds); infinite where
    unknown."""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("VmSize:"):
                    return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return math.inf
