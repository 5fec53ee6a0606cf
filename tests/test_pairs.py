"""Pair views of captures: per-view labels in the observer's frame, inputs, assemblies."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cadio.cad.ingest import IngestConfig, ingest
from cadio.cad.step import write_step
from cadio.capture.observe import observer_rotation
from cadio.capture.scan import (
    ScanConfig,
    assembly_pairs,
    capture_assembly,
    capture_scenes,
    scan_inputs,
)
from cadio.catalog import read_catalog
from cadio.evidence.cad_samples import surface_samples
from cadio.evidence.pairs import PairConfig, capture_pairs
from cadio.records import Relation
from cadio.sandbox import Limits
from cadio.truth.assemblies import assembly_jobs, mates_job
from cadio.truth.scene_config import SceneConfig
from cadio.truth.scenes import generate_scenes, read_scene_parts
from cadio.workspace import Workspace, read_mesh
from models.relation_inputs.completed import completion_builder
from models.relation_inputs.partial import observed_clouds
from models.relation_inputs.truth import truth_clouds

# The inputs every capture has (the CAD's samples and the observed points); ``completed``
# beside them where a test hands completions in.
STOCK = {"truth": truth_clouds, "partial": observed_clouds}


def _with_completions(done: dict) -> dict:
    return {**STOCK, "completed": completion_builder(done)}

# Two views on opposite sides of the circle (0 and 62 of 125: 178.6 degrees apart).
CFG = ScanConfig(views_per_scene=2, n_in=16, n_out=16, lengths=(), protocols=("observed",))
LEFT, RIGHT = list(Relation).index(Relation.LEFT), list(Relation).index(Relation.RIGHT)


@pytest.fixture(scope="module")
def ws(tmp_path_factory: pytest.TempPathFactory) -> Workspace:
    import build123d as bd

    lib = tmp_path_factory.mktemp("lib")
    (lib / "parts").mkdir()
    (lib / "assemblies").mkdir()
    write_step(bd.Box(30, 20, 10), lib / "parts" / "block.step")
    write_step(bd.Cylinder(6, 30), lib / "parts" / "pin.step")
    plate = bd.Box(60, 60, 5, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
    block = bd.Pos(0, 0, 5) * bd.Box(20, 20, 10,
                                     align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
    plate.label, block.label = "plate", "block"
    write_step(bd.Compound(children=[plate, block], label="stack"),
               lib / "assemblies" / "stack.step")
    space = Workspace(tmp_path_factory.mktemp("ws"))
    ingest(lib, space.root, IngestConfig(voxel_sizes=(16,), limits=Limits(workers=1)))
    return space


def _side_by_side(ws: Workspace) -> pd.DataFrame:
    """One scene: the block 80 mm at -X of the pin (left of it for an observer looking +Y)."""
    parts = read_scene_parts(read_catalog(ws.catalog), ws.root)
    scenes = generate_scenes(parts, SceneConfig(pairs_per_relation=1, val_fraction=0.0,
                                                test_fraction=0.0)).head(1).copy()
    block = next(p for p in parts if p.features.volume == pytest.approx(6000, rel=1e-3))
    pin = next(p for p in parts if p is not block)
    pose_a, pose_b = np.eye(4), np.eye(4)
    pose_a[:3, 3] = -block.features.centroid + [-80.0, 0.0, 0.0]
    pose_b[:3, 3] = -pin.features.centroid
    scenes.loc[scenes.index[0], ["part_a", "part_b", "category_a", "category_b",
                                 "scene_id"]] = [block.part_id, pin.part_id, "parts", "parts",
                                                 "side"]
    scenes.at[scenes.index[0], "pose_a"] = pose_a.ravel().tolist()
    scenes.at[scenes.index[0], "pose_b"] = pose_b.ravel().tolist()
    return scenes


def test_a_pair_seen_from_opposite_sides_swaps_left_and_right(ws: Workspace) -> None:
    captured = capture_scenes(_side_by_side(ws), read_catalog(ws.catalog), ws, CFG)
    assert captured[0].error == ""
    scan_inputs(Path(captured[0].path), ws, CFG)
    views = capture_pairs(Path(captured[0].path), ws, {}, PairConfig(), STOCK)
    assert [v.view for v in views] == [0, 1]  # numbered in capture order
    front, back = views
    assert front.labels[LEFT] and not front.labels[RIGHT]
    assert back.labels[RIGHT] and not back.labels[LEFT]
    symmetric = [list(Relation).index(r) for r in (Relation.PARALLEL, Relation.PERPENDICULAR,
                                                   Relation.CONCENTRIC, Relation.COINCIDENT)]
    assert np.array_equal(front.labels[symmetric], back.labels[symmetric])
    for view, sign in ((front, -1.0), (back, 1.0)):  # what the network sees agrees
        for name in ("truth", "partial"):
            obs = view.observer_points(name)
            assert obs.shape == (2, 600, 3)
            assert sign * (obs[0, :, 0].mean() - obs[1, :, 0].mean()) > 0.02


def test_a_part_beside_itself_is_two_instances(ws: Workspace) -> None:
    """Two instances of one part (a corpus may place a part twice) keep their own inputs and
    their own truth: the block 80 mm left of its twin is left of it."""
    scenes = _side_by_side(ws)
    first = scenes.index[0]
    block = scenes.at[first, "part_a"]
    scenes.loc[first, ["part_b", "scene_id"]] = [block, "twins"]
    pose_b = np.asarray(scenes.at[first, "pose_a"]).reshape(4, 4).copy()
    pose_b[0, 3] += 80.0
    scenes.at[first, "pose_b"] = pose_b.ravel().tolist()
    captured = capture_scenes(scenes, read_catalog(ws.catalog), ws, CFG)
    assert scan_inputs(Path(captured[0].path), ws, CFG).parts == 2
    views = capture_pairs(Path(captured[0].path), ws, {}, PairConfig(), STOCK)
    assert [v.view for v in views] == [0, 1]
    front, back = views
    assert front.part_a == front.part_b == block
    assert front.labels[LEFT] and back.labels[RIGHT]
    coincident = list(Relation).index(Relation.COINCIDENT)
    assert not front.labels[coincident]  # side by side on one plane: no face faces another
    for view, sign in ((front, -1.0), (back, 1.0)):
        for name in ("truth", "partial"):
            obs = view.observer_points(name)
            assert sign * (obs[0, :, 0].mean() - obs[1, :, 0].mean()) > 0.05


def test_pair_inputs_are_the_observed_points_and_the_cad_surface(ws: Workspace) -> None:
    captured = capture_scenes(_side_by_side(ws), read_catalog(ws.catalog), ws, CFG)
    scan_inputs(Path(captured[0].path), ws, CFG)
    view = capture_pairs(Path(captured[0].path), ws, {}, PairConfig(), STOCK)[0]
    partial, truth = view.points["partial"], view.points["truth"]
    # a single view sees one side of a part: its points span less depth than the surface's
    depth = np.ptp(view.observer_points("partial")[0, :, 1])
    assert depth < np.ptp(view.observer_points("truth")[0, :, 1])
    # the block is axis-aligned: every observed point lies on a face of the truth's box
    lo, hi = truth[0].min(axis=0), truth[0].max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    off_face = np.abs(np.abs(partial[0] - centre) - half).min(axis=1)
    inside = np.all(np.abs(partial[0] - centre) <= half + 0.02 * half.max(), axis=1)
    assert inside.mean() > 0.98 and np.median(off_face) < 0.01 * half.max()


def test_the_pair_evidence_reads_denser_clouds_than_the_network(ws: Workspace) -> None:
    from scipy.spatial import cKDTree

    from cadio.recordings.mcap_io import read_scene_meta

    captured = capture_scenes(_side_by_side(ws), read_catalog(ws.catalog), ws, CFG)
    path = Path(captured[0].path)
    scan_inputs(path, ws, CFG)
    # a completion of 5,000 points for every instance and view
    rng = np.random.default_rng(0)
    done = {(str(p["instance_id"]), v): rng.random((5000, 3)) * 0.05
            for p in read_scene_meta(path)["parts"] for v in range(CFG.views_per_scene)}
    view = capture_pairs(path, ws, {}, PairConfig(evidence_points=2000),
                         _with_completions(done))[0]
    a, b = view.evidence_clouds("truth")
    assert view.points["truth"].shape == (2, 600, 3) and len(a) == len(b) == 2000
    # the same surface placed the same way: the network's 600 samples lie on the 2,000, which
    # bring the unit normals of their CAD faces after their positions
    assert a.shape == (2000, 6) and np.allclose(np.linalg.norm(a[:, 3:], axis=1), 1.0, atol=1e-5)
    assert cKDTree(a[:, :3]).query(view.points["truth"][0])[0].max() < \
        0.05 * np.ptp(a[:, :3], axis=0).max()
    done_a, _ = view.evidence_clouds("completed")
    assert view.points["completed"].shape == (2, 600, 3) and len(done_a) == 2000
    assert len(np.unique(done_a, axis=0)) == 2000  # no repeats: a spacing of zero
    # a completion that gives normals: the network reads the positions, the evidence both
    normals = rng.normal(size=(5000, 3))
    with_normals = {k: np.hstack([pts, normals / np.linalg.norm(normals, axis=1, keepdims=True)])
                    for k, pts in done.items()}
    both = capture_pairs(path, ws, {}, PairConfig(evidence_points=2000),
                         _with_completions(with_normals))[0]
    assert np.array_equal(both.points["completed"], view.points["completed"])
    six, _ = both.evidence_clouds("completed")
    assert six.shape == (2000, 6) and np.array_equal(six[:, :3], done_a)
    # the observed points are the capture's: their evidence is measured on them
    assert np.array_equal(view.evidence_clouds("partial")[0], view.points["partial"][0])
    # truth knows the solids: its centres are their centroids (an axis-aligned block's: the
    # middle of its box), the other inputs' the means of their points
    lo, hi = a[:, :3].min(axis=0), a[:, :3].max(axis=0)
    assert np.allclose(view.centres["truth"][0], (lo + hi) / 2, atol=0.01 * np.ptp(a[:, :3]))
    assert np.allclose(view.observer_centres("truth"), view.centres["truth"]
                       @ observer_rotation(view.world_to_camera))
    assert np.allclose(view.observer_centres("partial"),
                       view.observer_points("partial").mean(axis=1))


def test_surface_samples_are_on_the_mesh_and_seeded(ws: Workspace) -> None:
    catalog = read_catalog(ws.catalog)
    mesh = read_mesh(ws.mesh(str(catalog["part_id"].iloc[0])))
    a, b = surface_samples(mesh, 500, 1), surface_samples(mesh, 500, 1)
    assert np.array_equal(a, b) and not np.array_equal(a, surface_samples(mesh, 500, 2))
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    assert np.all(a >= lo - 1e-9) and np.all(a <= hi + 1e-9)


def test_an_assembly_capture_labels_its_mated_pairs_in_every_view(ws: Workspace) -> None:
    job = assembly_jobs(read_catalog(ws.catalog), ws.root)[0]
    summary = mates_job(job)
    assert summary.ok and summary.face_mates >= 1
    mates = pd.read_parquet(ws.mates(job.assembly))
    pairs = assembly_pairs(mates)
    assert len(pairs) == 1 and set(pairs[0]) == set(job.part_ids.values())
    captured = capture_assembly(job.assembly, job.category, list(job.part_ids.values()), ws,
                                CFG)
    assert captured.error == "" and captured.input_parts == 2
    views = capture_pairs(Path(captured.path), ws, {}, PairConfig(), STOCK)
    assert len(views) == 2
    names = dict(zip(mates["part_a"], mates["name_a"], strict=False))
    above = list(Relation).index(Relation.ABOVE)
    coincident = list(Relation).index(Relation.COINCIDENT)
    for v in views:  # block on plate: above/below and coincident whatever the camera
        assert v.labels[above] == (names.get(v.part_a) == "block")
        assert v.labels[coincident]
    part = mates[mates.level == "part"]
    for v in views:  # the symmetric relations are the mates table's, in every view
        held = set(part[((part.part_a == v.part_a) & (part.part_b == v.part_b))
                        | ((part.part_a == v.part_b) & (part.part_b == v.part_a))].relation)
        for k, r in enumerate(Relation):
            if r in (Relation.CONCENTRIC, Relation.COINCIDENT, Relation.PARALLEL,
                     Relation.PERPENDICULAR):
                assert bool(v.labels[k]) == (r.value in held), r


def test_a_capture_without_inputs_gives_no_pair(ws: Workspace, tmp_path: Path) -> None:
    captured = capture_scenes(_side_by_side(ws), read_catalog(ws.catalog), ws, CFG)
    other = Workspace(tmp_path)  # the capture's inputs were never derived there
    for sub in ("features", "meshes"):
        (tmp_path / sub).symlink_to(ws.root / sub)
    assert capture_pairs(Path(captured[0].path), other, {}, PairConfig(), STOCK) == []
