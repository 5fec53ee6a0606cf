"""Job functions for the sandbox tests: they really crash, hang or exhaust memory."""

from __future__ import annotations

import ctypes
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from cadio.cad.ingest import IngestJob
    from cadio.catalog import CatalogRow


def misbehave(payload: str) -> str:
    """Do what the payload says; ``ok:<x>`` returns x."""
    if payload == "segfault":
        ctypes.string_at(0)  # a real SIGSEGV in this process
    if payload == "hang":
        time.sleep(3600)
    if payload == "memory":
        blocks = [bytearray(256 << 20) for _ in range(64)]  # 16 GB, far over the limit
        return str(len(blocks))
    if payload == "raise":
        raise ValueError("bad payload")
    return payload.removeprefix("ok:")


def process_or_crash(job: IngestJob) -> list[CatalogRow]:
    """The real per-file ingest job, except that a file named *segfault* crashes the process."""
    from cadio.cad.ingest import process_file

    if "segfault" in Path(job.path).name:
        ctypes.string_at(0)
    return process_file(job)
