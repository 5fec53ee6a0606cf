"""The capture stage end to end: scenes of ingested parts -> MCAP -> aligned learning inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import ndimage

from cadio.cad.ingest import IngestConfig, ingest
from cadio.capture.mcap_io import read_capture, read_scene_meta
from cadio.capture.scan import ScanConfig, capture_scenes, capture_step, scan_inputs, view_indices
from cadio.catalog import read_catalog
from cadio.sandbox import Limits
from cadio.truth.scenes import SceneConfig, generate_scenes, read_scene_parts, write_scenes
from cadio.workspace import Workspace, read_voxels

CFG = ScanConfig(views_per_scene=2, grid_sizes=(32,))


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
        bd.export_step(shape, lib / cat / f"{name}.step")
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


def test_inputs_are_aligned_with_the_truth_grid(ws: Workspace) -> None:
    scene = pd.read_parquet(ws.scenes).iloc[0]
    captured = capture_scenes(scene.to_frame().T, read_catalog(ws.catalog), ws, CFG)
    summary = scan_inputs(Path(captured[0].path), ws, CFG)
    assert summary.has_ids and summary.parts == 2
    assert summary.seg_mean_iou > 0.5
    for pid in (scene["part_a"], scene["part_b"]):
        with np.load(ws.inputs(str(scene["scene_id"]), pid)) as z:
            points = z["points"]
            partial = np.unpackbits(z["grid32"], count=32**3).astype(bool).reshape(32, 32, 32)
        truth = read_voxels(ws.voxels(pid, 32)).occupancy
        assert points.shape == (600, 3)
        assert partial.any()
        near_truth = ndimage.binary_dilation(truth, iterations=1)
        assert (partial & near_truth).sum() >= 0.95 * partial.sum()


def test_capture_a_step_file(tmp_path: Path, box_step: Path) -> None:
    summary = capture_step(str(box_step), tmp_path, ScanConfig(views_per_scene=3))
    assert summary.frames == 3 and summary.parts == 1
    frames = list(read_capture(Path(summary.path)))
    assert len(frames) == 3 and all((f.depth > 0).any() for f in frames)
