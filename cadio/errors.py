"""Errors raised by ``cadio``: one base class, small subclasses that say whose fault it is."""

from __future__ import annotations

from pathlib import Path


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
