"""Environment settings of mateqa (``MATEQA_*`` variables): the one place that reads them.

Library code never reads the environment; the CLI and the flows turn these settings into the
typed configuration of each stage (``ingest_config``), and command-line options override them.
"""

from __future__ import annotations

from pathlib import Path

from pydantic_settings import BaseSettings, SettingsConfigDict

from cadio.cad.ingest import IngestConfig
from cadio.sandbox import Limits
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances


class Settings(BaseSettings):
    """Where things live and how much of the machine a run may use."""

    model_config = SettingsConfigDict(env_prefix="MATEQA_")

    workspace: Path = Path("workspace")
    # Worker processes for CAD work; 0 means the caller's default (one per core for the CLI's
    # ingest, one per task in the flow, whose tasks already run side by side).
    workers: int = 0
    # Per-file limits of the isolated CAD reader.
    file_timeout_s: float = 300.0
    file_memory_mb: int = 6144
    max_file_mb: float = 200.0
    # Local Prefect server used when PREFECT_API_URL is not set.
    server_port: int = 4200
    prefect_home: Path = Path(".prefect")
    # A Dask scheduler the nightly's tasks run on (prefect-dask); empty: this machine.
    dask_address: str = ""

    def limits(self, default_workers: int = 1) -> Limits:
        """Worker limits of these settings (``workers`` 0 means ``default_workers``)."""
        return Limits(seconds=self.file_timeout_s, memory_mb=self.file_memory_mb,
                      workers=self.workers or default_workers)


def ingest_config(settings: Settings, voxel_sizes: list[int] | None = None,
                  tolerances: Tolerances = DEFAULT_TOLERANCES,
                  default_workers: int = 1) -> IngestConfig:
    """The ingest configuration for these settings, grid sizes and tolerances."""
    return IngestConfig(voxel_sizes=tuple(voxel_sizes or IngestConfig.voxel_sizes),
                        max_file_mb=settings.max_file_mb,
                        limits=settings.limits(default_workers), tolerances=tolerances)
