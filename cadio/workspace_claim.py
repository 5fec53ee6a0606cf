"""Claiming a workspace: one night at a time, and only a folder that is a workspace.

Two nights on one workspace (a scheduled one and one started by hand) would both write
``catalog.parquet`` and ``scenes.parquet`` and each report the other's parts. So a night, and
``mateqa ingest``, hold the workspace's lock (``.mateqa-lock``, an exclusive ``flock``) from
start to end; a second one is refused at once, naming the one that holds it (its pid, host,
start and what it runs), rather than made to wait: a night takes hours, and a command that
waits that long without a word reads as hung. The kernel drops the lock of a process that
dies, even by SIGKILL, so a killed night never leaves the workspace locked.

A workspace is also a folder mateqa may fill and clear. A night run with ``/`` or a home
folder as its workspace would write its catalog, meshes and runs among the system's files, so
a workspace must be new, empty, or one already (the marker ``.mateqa-workspace``, or only the
names a workspace holds), and never the filesystem's root or a system folder.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from cadio.errors import CadioError

LOCK = ".mateqa-lock"
MARKER = ".mateqa-workspace"
# What a workspace holds (``cadio.workspace``), so a folder of these alone is one already;
# hidden names are its own (the lock, the epoch, temporary files).
WORKSPACE_NAMES = frozenset({
    "catalog.parquet", "meshes", "features", "voxels", "mates", "scenes.parquet", "captures",
    "inputs", "relations", "runs", "library", "checkpoints", "datasets"})
# Folders that hold a system: never a workspace, even when empty.
SYSTEM_FOLDERS = frozenset(Path(p) for p in (
    "/", "/bin", "/boot", "/dev", "/etc", "/home", "/lib", "/lib32", "/lib64", "/libx32",
    "/media", "/mnt", "/opt", "/proc", "/root", "/run", "/sbin", "/srv", "/sys", "/tmp", "/usr",
    "/var", "/usr/local", "/var/tmp"))


class WorkspaceBusyError(CadioError):
    """Another process holds the workspace: ``holder`` is what it wrote of itself (pid, host,
    started, what)."""

    def __init__(self, workspace: Path | str, holder: Mapping[str, Any]) -> None:
        self.workspace, self.holder = str(workspace), dict(holder)
        super().__init__(f"{self.workspace} is in use by {describe(self.holder)}: one night "
                         "at a time per workspace; wait for it to end, or give another "
                         "workspace")

    def __reduce__(self) -> tuple[type[WorkspaceBusyError], tuple[Any, ...]]:
        return WorkspaceBusyError, (self.workspace, self.holder)


def describe(holder: Mapping[str, Any]) -> str:
    """``mateqa nightly (flow run 'mini-chital', pid 81 on qa-1, since 2026-11-28T02:00:00Z)``."""
    details = [f"flow run {holder['flow_run']!r}"] if holder.get("flow_run") else []
    details.append(f"pid {holder.get('pid', '?')} on {holder.get('host', '?')}")
    if holder.get("started"):
        details.append(f"since {holder['started']}")
    return f"{holder.get('what') or 'another mateqa command'} ({', '.join(details)})"


def workspace_problem(path: Path | str) -> str | None:
    """Why ``path`` may not be a workspace, or None when it may (see the module docstring)."""
    path = Path(path)
    real = path.resolve()
    if real in SYSTEM_FOLDERS or real == Path.home().resolve():
        what = "the filesystem root" if real == Path("/") else "a system folder"
        return f"{path} is {what}: a workspace is a folder of its own (a new or empty one)"
    if not path.is_dir():
        return None  # made by the run (``flows.preflight`` says whether it can be)
    try:
        names = [p.name for p in path.iterdir()]
    except OSError as exc:
        return f"{path} cannot be read: {exc.strerror or exc}"
    other = sorted(n for n in names if not n.startswith(".") and n not in WORKSPACE_NAMES)
    if other and MARKER not in names:
        return (f"{path} is not empty and not a mateqa workspace (it holds "
                f"{', '.join(other[:3])}{' ...' if len(other) > 3 else ''}): give a new or "
                "empty folder")
    latest = path / "runs" / "latest"
    if latest.exists() and not latest.is_symlink():
        return (f"{latest} is not the link to the newest run that mateqa keeps there: move "
                "it out of the way (a night would end without updating it)")
    return None


@contextmanager
def claim_workspace(root: Path, holder: Mapping[str, Any]) -> Iterator[dict[str, Any]]:
    """Hold ``root`` as a workspace for the block: it is made, marked and locked.

    Args:
        holder: what the lock tells a second claimant of its holder, beside the pid, host
            and start written here: ``what`` (e.g. "mateqa nightly"), ``flow_run``.

    Yields:
        The record written into the lock.

    Raises:
        WorkspaceBusyError: another process holds it.
        ValueError: ``root`` may not be a workspace (``workspace_problem``).
    """
    problem = workspace_problem(root)
    if problem:
        raise ValueError(problem)
    root.mkdir(parents=True, exist_ok=True)
    with os.fdopen(os.open(root / LOCK, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666),
                   "r+", encoding="utf-8") as fh:
        _lock(fh, root)
        record = {"pid": os.getpid(), "host": socket.gethostname(),
                  "started": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"), **holder}
        try:
            _write(fh, json.dumps(record))
            _mark(root)
            yield record
        finally:
            _write(fh, "")  # released: nothing to name
            fcntl.flock(fh, fcntl.LOCK_UN)


def _write(fh: IO[str], text: str) -> None:
    fh.seek(0)
    fh.truncate(0)
    fh.write(text)
    fh.flush()


def _lock(fh: IO[str], root: Path) -> None:
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        try:
            holder = json.loads(fh.read() or "{}")
        except ValueError:  # being written this instant: it is held all the same
            holder = {}
        raise WorkspaceBusyError(root, holder) from None


def _mark(root: Path) -> None:
    marker = root / MARKER
    if not marker.exists():
        marker.write_text("This folder is a mateqa workspace: mateqa reads and writes here.\n")
