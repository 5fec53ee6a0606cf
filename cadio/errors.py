"""Errors raised by ``cadio``: one base class, small subclasses that say whose fault it is."""

from __future__ import annotations

import errno
from pathlib import Path
from typing import Any


class CadioError(Exception):
    """Base class of every error raised by the CAD and capture I/O package."""


class InputFileError(CadioError):
    """An input file cannot be used; ``reason`` is a short human sentence."""

    def __init__(self, path: Path | str, reason: str) -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class StepReadError(InputFileError):
    """A STEP file could not be read into solids."""


class WorkerError(InputFileError):
    """The isolated worker process handling a file timed out, ran out of memory or crashed."""


class GeometryError(CadioError):
    """A shape could not be tessellated, voxelized or measured."""

    def __init__(self, what: str, reason: str) -> None:
        self.what = what
        self.reason = reason
        super().__init__(f"{what}: {reason}")


class CaptureError(InputFileError):
    """A capture (MCAP) file is truncated, corrupt, or has the wrong schema or topics."""


class CaptureTopicError(CaptureError):
    """A recording lacks a topic the reader needs, or a topic holds what it cannot read.

    topic: the topic at fault, or None when none was found; found: what the file holds there;
    expected: what the reader needs (schemas, encodings).
    """

    def __init__(self, path: Path | str, topic: str | None, found: str, expected: str) -> None:
        self.topic = topic
        self.found = found
        self.expected = expected
        where = f"topic {topic}: " if topic else ""
        super().__init__(path, f"{where}{found}; expected {expected}")


class CaptureTruncatedError(CaptureError):
    """A recording ends early or is damaged after ``messages`` complete messages (the frames
    before the damage were read); ``detail`` is what the MCAP reader found."""

    def __init__(self, path: Path | str, messages: int, detail: str) -> None:
        self.messages = messages
        self.detail = detail
        super().__init__(path, f"truncated or corrupt after {messages} complete messages "
                               f"({detail})")


class ExportError(InputFileError):
    """An assembly's predicted mates could not be exported (its inputs are missing or changed,
    or a file could not be written)."""


# What the machine, not an input, is at fault for: the disk or the quota is full, the
# filesystem is read-only or failing, or the workspace cannot be written by this user.
MACHINE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO, errno.EACCES,
                            errno.EPERM})


class MachineError(CadioError):
    """The machine stopped the work on ``path``, not the input being worked on: the disk is
    full, the workspace cannot be written, an I/O error. Never cached or reported as a bad
    input: the night that meets one fails, and the next one does the work again."""

    def __init__(self, path: Path | str, reason: str) -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")

    def __reduce__(self) -> tuple[type[MachineError], tuple[Any, ...]]:
        return MachineError, (self.path, self.reason)  # pickles with its fields (task results)

    @staticmethod
    def of(exc: OSError, path: Path | str) -> MachineError | None:
        """The machine's error behind ``exc`` met while writing ``path``; None when ``exc``
        is no fault of the machine (a file that does not exist, a name too long)."""
        if exc.errno not in MACHINE_ERRNOS:
            return None
        return MachineError(path, f"{exc.strerror or exc} (errno {exc.errno})")


class DiskSpaceError(MachineError):
    """Less space is free under ``path`` than a stage needs (checked before it starts):
    ``free_mb``, ``need_mb``, and ``what`` needs it."""

    def __init__(self, path: Path | str, free_mb: float, need_mb: float, what: str) -> None:
        self.free_mb, self.need_mb, self.what = free_mb, need_mb, what
        super().__init__(path, f"{free_mb:,.0f} MB free, but {what} need about "
                               f"{need_mb:,.0f} MB")

    def __reduce__(self) -> tuple[type[MachineError], tuple[Any, ...]]:
        return DiskSpaceError, (self.path, self.free_mb, self.need_mb, self.what)
