"""Errors raised by ``models``: one base class, small subclasses that say whose fault it is."""

from __future__ import annotations

from pathlib import Path


class ModelsError(Exception):
    """Base class of every error raised by the learned-model package."""


class FileFormatError(ModelsError):
    """A shard or checkpoint file cannot be used; ``reason`` is a short human sentence."""

    def __init__(self, path: Path | str, reason: str) -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class ShardError(FileFormatError):
    """A training shard (.npz) is unreadable or breaks the data contract."""


class CheckpointError(FileFormatError):
    """A checkpoint is unreadable, of another format, or does not match its model."""
