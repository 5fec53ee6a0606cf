"""How much disk the heavy stages of a night need, and the check made before each starts.

A full disk mid-stage stops the night with a ``MachineError`` (``cadio.workspace``), but only
after minutes of work, and the reason reads as a surprise. So ingest and the captures first
estimate what they will write, from measured sizes with room to spare, and a stage that would
not fit stops before it starts, saying how much is free and how much it needs. Work already on
disk (files ingested, captures rendered) is not counted again. The figures are estimates: a
disk that another program fills while the night runs still ends in a ``MachineError``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from cadio.errors import DiskSpaceError

MB = 1_000_000
# Meshes, features and voxels (32^3, 64^3) of 59 real STEP files (18.8 MB) took 10.5 MB: the
# library's own size again covers them, and 1 MB a file the larger grids (256^3 is ~0.1-2 MB
# a part) and the catalog.
INGEST_PER_STEP_BYTE = 1.0
INGEST_PER_FILE_MB = 1.0
# A rendered view of 640x480 takes about 10 kB of MCAP noise-free and 130 kB with the sensor
# noise (zstd compresses noise poorly), and its learning inputs about 70 kB: with room to spare.
VIEW_MB = 0.25
NOISY_VIEW_MB = 0.5
# Reports, relation rows and exports of a night, written after the captures.
REPORTS_MB = 50.0


def ingest_need_mb(files: list[Path]) -> float:
    """MB the ingest of ``files`` (not yet ingested) writes into the workspace, at most."""
    step_bytes = sum(_size(f) for f in files)
    return REPORTS_MB + INGEST_PER_STEP_BYTE * step_bytes / MB + INGEST_PER_FILE_MB * len(files)


def capture_need_mb(captures: int, views: int, noise: bool) -> float:
    """MB that ``captures`` new captures of ``views`` views each write, with their inputs."""
    return REPORTS_MB + captures * views * (NOISY_VIEW_MB if noise else VIEW_MB)


def free_mb(path: Path) -> float:
    """MB free to this user on the filesystem of ``path`` (or of its nearest existing parent:
    a workspace may not be made yet)."""
    path = Path(path).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free / MB


def check_free_space(path: Path, need_mb: float, what: str) -> float:
    """The MB free under ``path``, when at least ``need_mb``.

    Raises:
        DiskSpaceError: less is free; it names ``what`` needs the space, and how much.
    """
    free = free_mb(path)
    if free < need_mb:
        raise DiskSpaceError(path, free, need_mb, what)
    return free


def _size(path: Path) -> int:
    try:
        return Path(path).stat().st_size
    except OSError:  # a file that cannot be read becomes a row of its own at ingest
        return 0
