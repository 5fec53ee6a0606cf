"""The capture stage end to end: scenes of ingested parts -> MCAP -> aligned learning inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import ndimage

from cadio.cad.ingest import IngestConfig, file_sha256, ingest, part_id
from cadio.cad.step import write_step
from cadio.capture.examples import part_views, read_example
from cadio.capture.scan import (
    ScanConfig,
    capture_scenes,
    capture_step,
    part_examples,
    part_to_world,
    scan_inputs,
    view_indices,
)
from cadio.catalog import read_catalog
from cadio.recordings.mcap_io import read_capture, read_scene_meta
from cadio.sandbox import Limits
from cadio.truth.scene_config import SceneConfig
from cadio.truth.scenes import generate_scenes, read_scene_parts, write_scenes
from cadio.workspace import Workspace, read_mesh, read_voxels

CFG = ScanConfig(views_per_scene=2, n_in=32, n_out=32, lengths=(2,))


@pytest.fixture(scope="module")
def ws(tmp_path_factory: pytest.TempPathFactory) -> Workspace:
    import build123d as bd

    lib = tmp_path_factory.mktemp("lib")
    for cat, name, shape in [
        ("fasteners", "pin", bd.Cylinder(4, 30)),
        ("fasteners", "washer", bd.Cylinder(8, 2) - bd.Cylinder(4, 2)),
        ("linear-rotary-motion", "block", bd.Box(30, 20, 10)),
        ("linear-rotary-motion", "plate", bd.Box(40, 40, 4) - bd.Cylinder(5, 4)),
    ]:
        (lib / cat).mkdir(exist_ok=True)
        write_step(shape, lib / cat / f"{name}.step")  # fixed bytes: fixed ids and splits
    space = Workspace(tmp_path_factory.mktemp("ws"))
    ingest(lib, space.root, IngestConfig(voxel_sizes=(32,), limits=Limits(workers=2)))
    parts = read_scene_parts(read_catalog(space.catalog), space.root)
    scenes = generate_scenes(parts, SceneConfig(pairs_per_relation=1, val_fraction=0.0,
                                                test_fraction=0.0))
    write_scenes(space.scenes, scenes)
    return space


def test_views_are_spread_over_the_circle() -> None:
    assert view_indices(ScanConfig(views_per_scene=5)) == [0, 25, 50, 75, 100]
    assert view_indices(ScanConfig(views_per_scene=1)) == [0]


def test_scenes_capture_to_mcap_with_labels(ws: Workspace) -> None:
    scenes = pd.read_parquet(ws.scenes).head(3)
    captured = capture_scenes(scenes, read_catalog(ws.catalog), ws, CFG)
    assert [c.error for c in captured] == ["", "", ""]
    assert [c.frames for c in captured] == [2, 2, 2]
    for row, scene in zip(captured, scenes.to_dict("records"), strict=True):
        meta = read_scene_meta(Path(row.path))
        assert meta is not None
        assert meta["labels"]["pair"] == [scene["part_a"], scene["part_b"]]
        assert meta["labels"]["relations"]["left"] == bool(scene["left"])
        frames = list(read_capture(Path(row.path)))
        assert len(frames) == 2
        assert set(np.unique(frames[0].instance)) >= {1, 2}


def test_inputs_are_examples_of_each_part_in_both_protocols(ws: Workspace) -> None:
    scene = pd.read_parquet(ws.scenes).iloc[0]
    captured = capture_scenes(scene.to_frame().T, read_catalog(ws.catalog), ws, CFG)
    summary = scan_inputs(Path(captured[0].path), ws, CFG)
    assert summary.has_ids and summary.parts == 2
    # scored against the ids (segmentation quality itself is tested in test_pointcloud)
    assert 0.0 < summary.seg_mean_iou <= 1.0 and summary.clusters >= 1
    for instance, pid in enumerate((scene["part_a"], scene["part_b"]), start=1):
        folder = ws.inputs(str(scene["scene_id"]), instance)
        names = sorted(p.stem for p in folder.glob("*-*.npz"))
        assert all(n.startswith(("observed-", "oracle-box-")) for n in names)
        assert len(names) == summary.examples // 2 and names
        with np.load(folder / "points.npz") as z:
            assert z["points"].shape[1:] == (600, 3)
            assert len(z["view"]) == len(z["points"]) == len(z["world_to_camera"])
        truth = read_voxels(ws.voxels(pid, 32)).occupancy
        oracle = read_example(next(folder.glob("oracle-box-0.npz")))
        # the oracle-box protocol is the ingest's truth grid: seen surface sits on the truth,
        # and seen free space is outside it
        partial, free = oracle.inputs[0]
        assert partial.any() and oracle.target is not None
        assert np.array_equal(oracle.target, truth)
        near_truth = ndimage.binary_dilation(truth, iterations=1)
        assert (partial & near_truth).sum() >= 0.95 * partial.sum()
        assert free.any() and (free & ndimage.binary_erosion(truth)).sum() == 0


def test_observed_inputs_ignore_the_truth_in_the_capture(ws: Workspace) -> None:
    """Changing every truth field of the scene meta (poses, scale) changes the oracle-box
    examples and the targets, never the observed protocol's inputs."""
    scene = pd.read_parquet(ws.scenes).iloc[0]
    captured = capture_scenes(scene.to_frame().T, read_catalog(ws.catalog), ws, CFG)
    path = Path(captured[0].path)
    frames = list(read_capture(path))
    meta = read_scene_meta(path)
    assert meta is not None
    part = meta["parts"][0]
    views = part_views(frames, [f.instance for f in frames], int(part["instance_id"]))
    mesh = read_mesh(ws.mesh(str(part["part_id"])))
    honest = part_examples(views, mesh, part_to_world(meta, part), CFG)
    lied = {**meta, "scale_m_per_mm": 2 * meta["scale_m_per_mm"]}
    wrong_pose = np.asarray(part["pose_mm"]) @ np.diag([1, -1, -1, 1])
    wrong = part_examples(views, mesh, part_to_world(lied, {**part, "pose_mm": wrong_pose}), CFG)
    for name, example in honest.items():
        other = wrong[name]
        if name.startswith("observed"):
            assert np.array_equal(example.inputs, other.inputs)
            assert np.array_equal(example.depth, other.depth)
            assert np.array_equal(example.carve, other.carve)
            assert example.grid.grid_to_world(4) == pytest.approx(other.grid.grid_to_world(4))
            assert not np.array_equal(example.target, other.target)  # the truth did move
        else:  # the oracle-box grid goes with the part: the observed voxels move in it
            assert not np.array_equal(example.inputs, other.inputs)


def test_capture_a_step_file(tmp_path: Path, box_step: Path) -> None:
    summary = capture_step(str(box_step), tmp_path, ScanConfig(views_per_scene=3))
    assert summary.frames == 3 and summary.parts == 1
    frames = list(read_capture(Path(summary.path)))
    assert len(frames) == 3 and all((f.depth > 0).any() for f in frames)
    # its part is named as ingest names it, so a night reading the recording scores it
    meta = read_scene_meta(summary.path)
    assert meta is not None
    assert [p["part_id"] for p in meta["parts"]] == [part_id(file_sha256(box_step), 0)]


def test_a_part_a_capture_does_not_score_gets_only_its_views_inputs(ws: Workspace) -> None:
    """Scanned without scoring its parts, a capture keeps each view's observed input exactly
    as the scored example has it (what the relation stage completes) and drops the rest."""
    scene = pd.read_parquet(ws.scenes).iloc[0]
    captured = capture_scenes(scene.to_frame().T, read_catalog(ws.catalog), ws, CFG)
    path = Path(captured[0].path)
    full = scan_inputs(path, ws, CFG)
    folder = ws.inputs(path.stem, 1)  # instance 1: part a
    scored = {p.name: read_example(p) for p in folder.glob("observed-*.npz")}
    assert full.scored == (str(scene["part_a"]), str(scene["part_b"]))
    light = scan_inputs(path, ws, CFG, scored=())
    assert light.scored == () and light.examples == 0 and light.parts == full.parts
    names = sorted(p.name for p in folder.glob("*.npz"))
    singles = sorted(n for n in scored if n.count("-") == 1)
    assert names == sorted([*singles, "points.npz"]) and singles
    for name in singles:
        mine, theirs = read_example(folder / name), scored[name]
        assert mine.target is None and theirs.target is not None
        assert np.array_equal(mine.inputs, theirs.inputs)
        assert np.array_equal(mine.points, theirs.points)
        assert mine.grid.grid_to_world(4) == pytest.approx(theirs.grid.grid_to_world(4))
        assert mine.carve.size == 0 and mine.meta["input_only"]
