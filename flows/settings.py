"""Environment settings of mateqa (``MATEQA_*`` variables): the one place that reads them."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from pydantic_settings import BaseSettings, SettingsConfigDict

from cadio.cad.ingest import IngestConfig
from cadio.sandbox import Limits


class Settings(BaseSettings):
    """Where things live and how much of the machine a run may use."""

    model_config = SettingsConfigDict(env_prefix="MATEQA_")

    workspace: Path = Path("workspace")
    # Worker processes for CAD work; 0 means one per CPU core.
    workers: int = 0
    # Per-file limits of the isolated CAD reader.
    file_timeout_s: float = 300.0
    file_memory_mb: int = 6144
    max_file_mb: float = 200.0
    # Local Prefect server used when PREFECT_API_URL is not set.
    server_port: int = 4200
    prefect_home: Path = Path(".prefect")


def ingest_config(settings: Settings, voxel_sizes: list[int] | None = None,
                  default_workers: int = 1) -> IngestConfig:
    """The ingest configuration for these settings (``workers`` 0 means ``default_workers``)."""
    limits = Limits(seconds=settings.file_timeout_s, memory_mb=settings.file_memory_mb,
                    workers=settings.workers or default_workers)
    cfg = IngestConfig(limits=limits, max_file_mb=settings.max_file_mb)
    return replace(cfg, voxel_sizes=tuple(voxel_sizes)) if voxel_sizes else cfg
