"""Shared pytest fixtures for mateqa's tests."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_STEP_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "step"


@pytest.fixture(scope="session")
def shared_step_dir() -> Path:
    """The folder of real STEP files (../shared/data/step); skips the test when it is absent."""
    if not SHARED_STEP_DIR.is_dir():
        pytest.skip(f"real STEP files not found at {SHARED_STEP_DIR}")
    return SHARED_STEP_DIR


@pytest.fixture(scope="session")
def step_solids(shared_step_dir: Path):  # type: ignore[no-untyped-def]
    """A cached loader: relative path under the shared STEP folder -> its TopoDS_Solids.

    Reads with build123d (not the project's reader) so geometry tests stand on their own.
    """
    import build123d

    cache: dict[str, list] = {}

    def load(relative: str) -> list:
        if relative not in cache:
            shape = build123d.import_step(shared_step_dir / relative)
            cache[relative] = [s.wrapped for s in shape.solids()]
        return cache[relative]

    return load


@pytest.fixture(scope="session")
def manifest(shared_step_dir: Path):  # type: ignore[no-untyped-def]
    """MANIFEST.csv of the real STEP files, indexed by path relative to the step folder."""
    import pandas as pd

    frame = pd.read_csv(shared_step_dir.parent / "MANIFEST.csv")
    frame["relative"] = frame["file"].str.removeprefix("step/")
    return frame.set_index("relative")


@pytest.fixture(scope="session")
def box_step(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small valid STEP part (a 20 x 10 x 5 mm box with a 4 mm hole), made with build123d.

    Written with a fixed header time stamp: its content hash, hence its part id and its
    train/val/test split, is the same in every session.
    """
    import build123d as bd

    from cadio.cad.step import write_step

    path = tmp_path_factory.mktemp("box") / "box.step"
    part = bd.Box(20, 10, 5) - bd.Cylinder(2, 5)
    part.label = "box"
    write_step(part, path)
    return path
