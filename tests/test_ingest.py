"""Ingest: every file found is accounted for; bad input becomes a clear row, never a crash."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from sandbox_targets import process_on_a_full_disk, process_or_crash

from cadio.cad.ingest import IngestConfig, discover, ingest, largest_first
from cadio.catalog import read_catalog
from cadio.errors import InputFileError
from cadio.sandbox import Job, Limits
from cadio.workspace import Workspace, read_features, read_mesh, read_voxels

FAST = IngestConfig(voxel_sizes=(32,), limits=Limits(seconds=120, workers=2))


def _face_only_step(path: Path) -> None:
    import build123d as bd

    bd.export_step(bd.Rectangle(10, 10), path)


@pytest.fixture(scope="module")
def bad_library(tmp_path_factory: pytest.TempPathFactory, box_step: Path) -> Path:
    """A library holding one good part and every kind of bad input of the issue."""
    root = tmp_path_factory.mktemp("lib")
    cat = root / "fasteners"
    cat.mkdir()
    good = box_step.read_bytes()
    (cat / "good.step").write_bytes(good)
    (cat / "écrou_ß_螺母.STP").write_bytes(good.replace(b"box", b"nut"))
    (cat / "empty.step").write_bytes(b"")
    (cat / "random.step").write_bytes(np.random.default_rng(0).bytes(4096))
    (cat / "truncated.step").write_bytes(good[: len(good) // 2])
    (cat / "not-step.step").write_text("solid cube\n  facet normal 0 0 1\nendsolid cube\n")
    _face_only_step(cat / "no-solids.step")
    (cat / "dir.step").mkdir()
    (cat / "dangling.step").symlink_to(cat / "does-not-exist.step")
    (cat / "big.step").write_bytes(good + b"\n" * 3_000_000)
    (root / "nested" / "deeper").mkdir(parents=True)
    shutil.copy(box_step, root / "nested" / "deeper" / "copy.Step")
    return root


@pytest.fixture(scope="module")
def bad_catalog(bad_library: Path, tmp_path_factory: pytest.TempPathFactory) -> pd.DataFrame:
    ws = tmp_path_factory.mktemp("ws")
    return ingest(bad_library, ws, replace(FAST, max_file_mb=2.0))


def _row(catalog: pd.DataFrame, name: str) -> pd.Series:
    rows = catalog[catalog["source"].str.endswith(name)]
    assert len(rows) == 1, f"{name}: {len(rows)} rows"
    return rows.iloc[0]


def test_every_file_found_is_accounted_for(bad_library: Path, bad_catalog: pd.DataFrame) -> None:
    found = {str(f.path) for f in discover(bad_library)}
    assert len(found) == 11
    assert set(bad_catalog["source"]) == found
    per_file = bad_catalog.groupby("source")["status"].first()
    counts = per_file.value_counts()
    assert counts.get("ok", 0) + counts.get("failed", 0) + counts.get("skipped", 0) == len(found)


@pytest.mark.parametrize(
    ("name", "status", "reason"),
    [
        ("empty.step", "failed", "empty file"),
        ("random.step", "failed", "not a STEP file"),
        ("truncated.step", "failed", "truncated"),
        ("not-step.step", "failed", "not a STEP file"),
        ("no-solids.step", "failed", "holds no solid"),
        ("dir.step", "skipped", "is a directory"),
        ("dangling.step", "failed", "cannot be read"),
        ("big.step", "skipped", "over the 2 MB limit"),
    ],
)
def test_bad_input_gets_a_clear_row(
    bad_catalog: pd.DataFrame, name: str, status: str, reason: str
) -> None:
    row = _row(bad_catalog, name)
    assert row["status"] == status
    assert reason in row["error"]
    assert row["category"] == "fasteners"


def test_good_files_ingest_including_non_ascii_names_and_nesting(
    bad_catalog: pd.DataFrame,
) -> None:
    for name in ("good.step", "écrou_ß_螺母.STP"):
        row = _row(bad_catalog, name)
        assert row["status"] == "ok" and row["error"] == ""
        assert row["volume"] == pytest.approx(20 * 10 * 5 - np.pi * 4 * 5, rel=1e-6)
    nested = _row(bad_catalog, "copy.Step")
    assert nested["category"] == "nested"
    # same bytes as good.step: reported as a duplicate rather than ingested twice
    assert nested["status"] == "skipped" and "duplicate of" in nested["error"]


def test_unreadable_file_without_permission(tmp_path: Path, box_step: Path) -> None:
    if os.geteuid() == 0:
        pytest.skip("root reads files whatever their mode; the dangling link covers this case")
    lib = tmp_path / "lib" / "fasteners"
    lib.mkdir(parents=True)
    target = lib / "locked.step"
    shutil.copy(box_step, target)
    target.chmod(0)
    catalog = ingest(lib.parent, tmp_path / "ws", FAST)
    assert "cannot be read" in _row(catalog, "locked.step")["error"]


def test_artefacts_are_written_and_consistent(tmp_path: Path, box_step: Path) -> None:
    lib = tmp_path / "lib" / "linear-rotary-motion"
    lib.mkdir(parents=True)
    shutil.copy(box_step, lib / "box.step")
    ws = Workspace(tmp_path / "ws")
    catalog = ingest(lib.parent, ws.root, FAST)
    row = catalog.iloc[0]
    pid = row["part_id"]
    mesh = read_mesh(ws.mesh(pid))
    features = read_features(ws.features(pid))
    grid = read_voxels(ws.voxels(pid, 32))
    assert len(mesh.triangles) == row["n_triangles"] > 0
    assert features.volume == pytest.approx(row["volume"])
    assert abs(row["volume_rel_error"]) < 0.01
    occupied = grid.occupancy.sum() * grid.voxel_size**3
    assert occupied == pytest.approx(row["volume"], rel=0.15)
    assert read_catalog(ws.catalog)["part_id"].tolist() == [pid]


def test_rerun_reuses_unchanged_files(tmp_path: Path, box_step: Path) -> None:
    lib = tmp_path / "lib" / "fasteners"
    lib.mkdir(parents=True)
    shutil.copy(box_step, lib / "a.step")
    ws = tmp_path / "ws"
    first = ingest(lib.parent, ws, FAST)
    assert not first["cached"].any()
    (lib / "b.step").write_bytes(box_step.read_bytes().replace(b"box", b"bbb"))
    second = ingest(lib.parent, ws, FAST)
    by_name = {Path(s).name: c for s, c in zip(second["source"], second["cached"], strict=True)}
    assert by_name == {"a.step": True, "b.step": False}


def test_a_real_reader_crash_does_not_stop_the_batch(tmp_path: Path, box_step: Path) -> None:
    lib = tmp_path / "lib" / "fasteners"
    lib.mkdir(parents=True)
    shutil.copy(box_step, lib / "before.step")
    (lib / "segfault.step").write_bytes(box_step.read_bytes().replace(b"box", b"seg"))
    (lib / "zafter.step").write_bytes(box_step.read_bytes().replace(b"box", b"aft"))
    cfg = replace(FAST, worker=process_or_crash,
                  limits=Limits(seconds=120, workers=1))
    catalog = ingest(lib.parent, tmp_path / "ws", cfg)
    crashed = _row(catalog, "segfault.step")
    assert crashed["status"] == "failed" and "SIGSEGV" in crashed["error"]
    assert _row(catalog, "before.step")["status"] == "ok"
    assert _row(catalog, "zafter.step")["status"] == "ok"


def test_jobs_start_with_the_largest_file(tmp_path: Path) -> None:
    sizes = {"small.step": 10, "large.step": 3000, "middle.step": 200, "also-middle.step": 200}
    for name, size in sizes.items():
        (tmp_path / name).write_bytes(b"x" * size)
    jobs = [Job(str(tmp_path / name), name) for name in sizes]
    order = [job.payload for job in largest_first(jobs)]
    assert order == ["large.step", "also-middle.step", "middle.step", "small.step"]


def test_the_supervisor_and_fresh_workers_load_no_heavy_library() -> None:
    """The supervisor has no use for them, and a fresh worker imports the job's module (here
    ingest's) before its first file."""
    heavy = ("OCP", "open3d", "pandas", "pydantic")
    probe = ("import sys, flows.cli, cadio.cad.ingest; "
             f"print(sorted(m for m in {heavy} if m in sys.modules))")
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True, cwd=root, env={**os.environ, "PYTHONPATH": str(root)})
    assert out.stdout.strip() == "[]"


def test_a_library_csv_names_files_and_categories(box_step: Path, tmp_path: Path) -> None:
    listing = tmp_path / "library.csv"
    listing.write_text(f"path,category\n{box_step},plates\nmissing.step,fasteners\n")
    found = discover(listing)
    assert [(f.path, f.category) for f in found] == [
        (box_step, "plates"), (tmp_path / "missing.step", "fasteners")]
    bad = tmp_path / "bad.csv"
    bad.write_text("file,kind\nx.step,a\n")
    with pytest.raises(InputFileError, match=r"bad\.csv.*path and category"):
        discover(bad)


def test_a_linked_category_folder_is_searched_and_a_link_loop_searched_once(
        tmp_path: Path, box_step: Path) -> None:
    lib, elsewhere = tmp_path / "lib", tmp_path / "elsewhere" / "couplings"
    (lib / "fasteners" / "sub").mkdir(parents=True)
    elsewhere.mkdir(parents=True)
    shutil.copy(box_step, lib / "fasteners" / "box.step")
    (elsewhere / "pin.step").write_bytes(box_step.read_bytes().replace(b"box", b"pin"))
    (lib / "couplings").symlink_to(elsewhere, target_is_directory=True)
    (lib / "fasteners" / "sub" / "up").symlink_to("..", target_is_directory=True)
    (lib / "fasteners" / "root").symlink_to("/", target_is_directory=True)
    catalog = ingest(lib, tmp_path / "ws", FAST)
    linked = _row(catalog, "couplings/pin.step")
    assert linked["status"] == "ok" and linked["category"] == "couplings"
    assert _row(catalog, "fasteners/box.step")["status"] == "ok"
    for loop in ("sub/up", "fasteners/root"):
        row = _row(catalog, loop)
        assert row["status"] == "skipped" and "searched once" in row["error"], row["error"]
    assert len(catalog) == 4  # every path found is accounted for, each once


def test_a_folder_that_cannot_be_read_is_a_failed_row(tmp_path: Path, box_step: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    lib = tmp_path / "lib"
    (lib / "fasteners").mkdir(parents=True)
    (lib / "couplings").mkdir()
    shutil.copy(box_step, lib / "fasteners" / "box.step")
    shutil.copy(box_step, lib / "couplings" / "hidden.step")
    locked = lib / "couplings"
    locked.chmod(0)
    if os.geteuid() == 0:  # root reads any folder: refuse this one as the kernel would
        import cadio.cad.ingest as module

        real = os.scandir

        def scandir(path: object) -> object:
            if Path(str(path)) == locked:
                raise PermissionError(13, "Permission denied", str(path))
            return real(path)  # type: ignore[arg-type]

        monkeypatch.setattr(module.os, "scandir", scandir)
    try:
        catalog = ingest(lib, tmp_path / "ws", FAST)
    finally:
        locked.chmod(0o755)
    row = _row(catalog, "couplings")
    assert row["status"] == "failed" and row["category"] == "couplings"
    assert "folder cannot be read (Permission denied)" in row["error"]
    assert _row(catalog, "box.step")["status"] == "ok"


def test_a_full_disk_is_no_failed_file_and_the_next_ingest_reads_every_file(
        tmp_path: Path, box_step: Path) -> None:
    from cadio.errors import MachineError

    lib = tmp_path / "lib" / "fasteners"
    lib.mkdir(parents=True)
    shutil.copy(box_step, lib / "box.step")
    ws = tmp_path / "ws"
    with pytest.raises(MachineError, match="No space left on device"):
        ingest(lib.parent, ws, replace(FAST, worker=process_on_a_full_disk))
    assert read_catalog(ws / "catalog.parquet").empty  # no row says the file is bad
    catalog = ingest(lib.parent, ws, FAST)  # the disk freed: the file is read again
    assert list(catalog["status"]) == ["ok"] and not catalog["cached"].any()
