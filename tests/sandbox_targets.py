"""Job functions for the sandbox tests: they really crash, hang or exhaust memory."""

from __future__ import annotations

import ctypes
import errno
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from multiprocessing.queues import Queue

    from cadio.cad.ingest import IngestJob
    from cadio.catalog import CatalogRow
    from cadio.sandbox import Limits


_HELD: list[object] = []  # what ``hold:`` jobs left mapped in this worker


def misbehave(payload: str) -> str:
    """Do what the payload says; ``ok:<x>`` returns x, ``pid`` the worker's process id."""
    if payload == "segfault":
        ctypes.string_at(0)  # a real SIGSEGV in this process
    if payload == "hang":
        time.sleep(3600)
    if payload == "memory":
        blocks = [bytearray(256 << 20) for _ in range(64)]  # 16 GB, far over the limit
        return str(len(blocks))
    if payload == "raise":
        raise ValueError("bad payload")
    if payload == "pid":
        return str(os.getpid())
    if payload == "where":  # what a worker takes from its supervisor when it starts
        import sys

        umask = os.umask(0)
        os.umask(umask)
        return f"{os.getcwd()}|{umask:o}|{sys.path[0]}|{os.environ.get('SANDBOX_TEST', '')}"
    if payload.startswith("hold:"):  # map this many MB and keep them mapped after the job
        import mmap

        _HELD.append(mmap.mmap(-1, int(payload.removeprefix("hold:")) << 20))
        return str(os.getpid())
    if payload == "limit":  # the worker and the address-space limit its job runs under, MB
        import resource

        return f"{os.getpid()}:{resource.getrlimit(resource.RLIMIT_AS)[0] >> 20}"
    if payload.startswith("env:"):
        return os.environ.get(payload.removeprefix("env:"), "")
    if payload == "full-disk":  # a write the disk refuses, as a full one does
        from cadio.workspace import atomic_write

        with atomic_write(Path(os.environ.get("TMPDIR", "/tmp")) / "never-written"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return payload.removeprefix("ok:")


def process_or_crash(job: IngestJob) -> list[CatalogRow]:
    """The real per-file ingest job, except that a file named *segfault* crashes the process."""
    from cadio.cad.ingest import process_file

    if "segfault" in Path(job.path).name:
        ctypes.string_at(0)
    return process_file(job)


def process_on_a_full_disk(job: IngestJob) -> list[CatalogRow]:
    """The real per-file ingest job, on a disk that refuses every write as a full one does."""
    from unittest import mock

    from cadio.cad.ingest import process_file

    def full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with mock.patch("cadio.workspace.create_beside", full):
        return process_file(job)


def run_in_daemon(payloads: list[str], limits: Limits, out: Queue) -> None:
    """Run ``misbehave`` on the payloads through the sandbox from this (daemonic) process, as
    a ``dask worker`` process does; put {payload: result or error reason} and whether this
    process is daemonic on ``out``."""
    import multiprocessing

    from cadio.sandbox import Job, run_isolated

    found = {}
    for o in run_isolated(misbehave, [Job(p, p) for p in payloads], limits):
        found[o.job.key] = o.result if o.error is None else f"error: {o.error.reason}"
    out.put((multiprocessing.current_process().daemon, found))
