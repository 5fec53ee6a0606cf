"""The disk a night's heavy stages need, checked before each starts."""

from __future__ import annotations

import pickle
import shutil
from collections import namedtuple
from pathlib import Path

import pytest

from cadio.disk_space import (
    MB,
    REPORTS_MB,
    VIEW_MB,
    capture_need_mb,
    check_free_space,
    free_mb,
    ingest_need_mb,
)
from cadio.errors import DiskSpaceError, MachineError

Usage = namedtuple("Usage", "total used free")


def test_the_need_grows_with_the_files_and_the_views(tmp_path: Path) -> None:
    step = tmp_path / "a.step"
    step.write_bytes(b"x" * 3 * int(MB))
    assert ingest_need_mb([step]) == pytest.approx(REPORTS_MB + 3 + 1)
    assert ingest_need_mb([]) == REPORTS_MB
    assert capture_need_mb(10, 8, noise=False) == pytest.approx(REPORTS_MB + 80 * VIEW_MB)
    assert capture_need_mb(10, 8, noise=True) > capture_need_mb(10, 8, noise=False)


def test_a_workspace_not_yet_made_is_measured_on_its_parent(tmp_path: Path) -> None:
    assert free_mb(tmp_path / "ws" / "deeper") == pytest.approx(free_mb(tmp_path), rel=0.01)


def test_too_little_space_is_a_machine_error_with_the_figures(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(shutil, "disk_usage", lambda path: Usage(10**9, 10**9 - 20 * MB,
                                                                 20 * MB))
    assert check_free_space(tmp_path, 19.5, "a test") == pytest.approx(20)
    with pytest.raises(DiskSpaceError) as err:
        check_free_space(tmp_path, 52, "the 2 new STEP file(s) to ingest")
    assert isinstance(err.value, MachineError)
    assert str(err.value) == (f"{tmp_path}: 20 MB free, but the 2 new STEP file(s) to ingest "
                              "need about 52 MB")
    again = pickle.loads(pickle.dumps(err.value))  # a task's error crosses processes
    assert type(again) is DiskSpaceError and str(again) == str(err.value)
