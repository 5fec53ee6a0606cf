"""Environment settings of mateqa (``MATEQA_*`` variables): the one place that reads them.

Library code never reads the environment; the CLI and the flows turn these settings into the
typed configuration of each stage (``ingest_config``), and command-line options override them.
The ranges below are the only ones: the night's configuration (``flows.config``) and the CLI
take theirs from these types, so an option, a deployment parameter and a variable of the
environment are held to the same limits.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

from pydantic import Field, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict

from cadio.cad.ingest import IngestConfig
from cadio.sandbox import Limits
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances

if TYPE_CHECKING:
    from flows.config import RuntimeOptions

# CAD worker processes (0: the caller's default, see ``Settings.workers``).
Workers = Annotated[int, Field(ge=0, le=256)]
# Seconds one file may take in its worker: a 10 MB STEP reads in seconds, so above a day is a
# typo; 0 would fail every file.
FileSeconds = Annotated[float, Field(gt=0, le=86_400)]
# Address space of a CAD worker: OCP, open3d and NumPy map about 1.5 GB at idle, so less than
# 2 GB fails every file.
MemoryMB = Annotated[int, Field(ge=2048, le=4_194_304)]
# Files larger than this are skipped without being read.
FileMB = Annotated[float, Field(gt=0, le=1_000_000)]
Port = Annotated[int, Field(ge=1, le=65_535)]


class SettingsError(ValueError):
    """An environment variable that does not validate; the message names it and the reason."""


class Settings(BaseSettings):
    """Where things live and how much of the machine a run may use."""

    model_config = SettingsConfigDict(env_prefix="MATEQA_")

    workspace: Path = Path("workspace")
    # Worker processes for CAD work; 0 means the caller's default (one per core for the CLI's
    # ingest, one per task in the flow, whose tasks already run side by side).
    workers: Workers = 0
    # Per-file limits of the isolated CAD reader.
    file_timeout_s: FileSeconds = 300.0
    file_memory_mb: MemoryMB = 6144
    max_file_mb: FileMB = 200.0
    # Local Prefect server used when PREFECT_API_URL is not set.
    server_port: Port = 4200
    prefect_home: Path = Path(".prefect")
    # A Dask scheduler the nightly's tasks run on (prefect-dask); empty: this machine.
    dask_address: str = ""

    def limits(self, default_workers: int = 1) -> Limits:
        """Worker limits of these settings (``workers`` 0 means ``default_workers``)."""
        return Limits(seconds=self.file_timeout_s, memory_mb=self.file_memory_mb,
                      workers=self.workers or default_workers)


def load_settings() -> Settings:
    """The settings of the environment.

    Raises:
        SettingsError: a ``MATEQA_*`` variable out of its range or of the wrong type (the
            message names the variable, the reason and the value).
    """
    try:
        return Settings()
    except ValidationError as exc:
        problems = [f"MATEQA_{'_'.join(map(str, e['loc'])).upper()}={e['input']!r}: {e['msg']}"
                    for e in exc.errors()]
        raise SettingsError("; ".join(problems)) from None


def runtime_settings(runtime: RuntimeOptions) -> Settings:
    """The environment's settings with a run's runtime options on top (an option not given
    keeps the environment's)."""
    env = load_settings()
    return env.model_copy(update={
        "workers": env.workers if runtime.workers is None else runtime.workers,
        "file_timeout_s": runtime.file_timeout_s or env.file_timeout_s,
        "file_memory_mb": runtime.file_memory_mb or env.file_memory_mb,
        "max_file_mb": runtime.max_file_mb or env.max_file_mb})


def ingest_config(settings: Settings, voxel_sizes: list[int] | None = None,
                  tolerances: Tolerances = DEFAULT_TOLERANCES,
                  default_workers: int = 1) -> IngestConfig:
    """The ingest configuration for these settings, grid sizes and tolerances."""
    return IngestConfig(voxel_sizes=tuple(voxel_sizes or IngestConfig.voxel_sizes),
                        max_file_mb=settings.max_file_mb,
                        limits=settings.limits(default_workers), tolerances=tolerances)
