"""Tests of cadio.capture.observe and .examples: grids placed from what a camera knows."""

from __future__ import annotations

import inspect
import math
from dataclasses import replace

import numpy as np
import open3d as o3d
import pytest

from cadio.cad.voxels import voxelize
from cadio.camera.render import CaptureConfig, camera_pose
from cadio.capture.examples import (
    ExampleConfig,
    observed_example,
    oracle_example,
    read_example,
    render_part_views,
    view_sets,
    with_truth,
    write_example,
)
from cadio.capture.observe import (
    FREE,
    SURFACE,
    CubeGrid,
    PartGrids,
    camera_azimuth_deg,
    carve,
    depth_view,
    observed_occupancy,
    observer_rotation,
    occluded_sides,
    oracle_grid,
    place_grid,
    truth_occupancy,
    view_states,
)
from cadio.records import Mesh

CAPTURE = CaptureConfig()
SMALL = ExampleConfig(n_in=16, n_out=32)


def _box(x: float, y: float, z: float) -> Mesh:
    m = o3d.geometry.TriangleMesh.create_box(x, y, z)
    return Mesh(np.asarray(m.vertices, dtype=np.float64), np.asarray(m.triangles, dtype=np.int64))


def _pose(yaw_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    p = np.eye(4)
    p[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    p[:3, 3] = t
    return p


@pytest.fixture(scope="module")
def box_views():  # type: ignore[no-untyped-def]
    mesh = _box(60, 40, 30)
    views, to_world = render_part_views(mesh, _pose(20, (-30, -20, 0)), [0, 16, 31, 47],
                                        CAPTURE)
    return mesh, views, to_world


def test_observer_frame_follows_the_camera() -> None:
    for view in (0, 31, 62):
        w2c = camera_pose(CAPTURE, view, np.zeros(3))
        rot = observer_rotation(w2c)
        forward = w2c[2, :3]
        behind = rot[:, 1]
        assert rot.T @ rot == pytest.approx(np.eye(3), abs=1e-12)
        assert rot[:, 2] == pytest.approx([0, 0, 1])
        assert behind @ forward > 0 and abs(behind[2]) < 1e-12
        assert camera_azimuth_deg(w2c) == pytest.approx(view * CAPTURE.step_deg % 360)


def test_the_grid_holds_what_was_seen_and_room_behind(box_views) -> None:  # type: ignore[no-untyped-def]
    _, views, _ = box_views
    grid = place_grid(views[0].points, views[0].evidence.world_to_camera)
    g = grid.to_grid(views[0].points)
    assert np.all((g >= 0) & (g <= 1))
    assert np.median(g[:, 1]) < 0.5  # the camera sees the front: the rest of the cube is behind
    shift = np.array([0.1, -0.2, 0.3])
    moved = place_grid(views[0].points + shift, views[0].evidence.world_to_camera)
    assert moved.side == pytest.approx(grid.side)
    assert moved.corner == pytest.approx(grid.corner + shift)


def test_observed_inputs_take_no_truth(box_views) -> None:  # type: ignore[no-untyped-def]
    """The observed protocol's signature takes views alone, and its result does not change
    when the part is the same but its hidden pose and mesh are others."""
    assert list(inspect.signature(observed_example).parameters) == ["views", "cfg"]
    mesh, views, to_world = box_views
    a = observed_example(views[:2], SMALL)
    b = observed_example(views[:2], SMALL)
    truthful = with_truth(a, mesh, to_world, SMALL)
    assert np.array_equal(a.inputs, b.inputs) and np.array_equal(a.carve, b.carve)
    assert np.array_equal(truthful.inputs, a.inputs) and truthful.target is not None
    other = oracle_example(views[:2], mesh, _pose(40, (0, 0, 0)) @ to_world, SMALL)
    assert not np.allclose(other.grid.corner, oracle_example(views[:2], mesh, to_world,
                                                             SMALL).grid.corner)


def test_the_oracle_grid_is_the_ingest_truth_grid(box_views) -> None:  # type: ignore[no-untyped-def]
    mesh, _, to_world = box_views
    truth = voxelize(mesh, 32, margin=SMALL.grid_margin)
    grid = oracle_grid(mesh, to_world, SMALL.grid_margin)
    assert grid.grid_to_world(32) == pytest.approx(to_world @ truth.grid_to_part, abs=1e-12)
    assert np.array_equal(truth_occupancy(mesh, to_world, grid, 32), truth.occupancy)


def test_the_target_fills_the_observed_surface(box_views) -> None:  # type: ignore[no-untyped-def]
    mesh, views, to_world = box_views
    example = with_truth(observed_example(views[:1], SMALL), mesh, to_world, SMALL)
    assert example.target is not None and example.coverage > 0.95
    near = example.target | np.roll(example.target, 1, 0) | np.roll(example.target, -1, 0)
    near |= np.roll(near, 1, 1) | np.roll(near, -1, 1) | np.roll(near, 1, 2) | np.roll(near, -1, 2)
    assert (example.visible & near).sum() >= 0.9 * example.visible.sum()


def test_carving_more_views_agrees_better_with_the_box(box_views) -> None:  # type: ignore[no-untyped-def]
    mesh, views, to_world = box_views

    def iou(n_views: int) -> float:
        ex = with_truth(oracle_example(views[:n_views], mesh, to_world, SMALL), mesh, to_world,
                        SMALL)
        assert ex.target is not None
        return float((ex.carve & ex.target).sum() / (ex.carve | ex.target).sum())

    one, four = iou(1), iou(4)
    assert four > one and four > 0.6


def test_depth_view_of_a_wall_is_flat() -> None:
    grid = CubeGrid(np.eye(3), np.zeros(3), 1.0)
    xs, zs = np.meshgrid(np.linspace(0.01, 0.99, 200), np.linspace(0.01, 0.49, 100))
    wall = np.column_stack([xs.ravel(), np.full(xs.size, 0.26), zs.ravel()])
    img = depth_view(observed_occupancy(wall, grid, 16))
    seen = img[1] > 0
    assert seen[:, :8].all() and not seen[:, 8:].any()
    assert img[0][seen] == pytest.approx(4.5 / 16) and (img[0][~seen] == 1).all()
    occ = observed_occupancy(wall, grid, 8)
    assert occ[:, 2, :4].all() and occ.sum() == 32


def test_examples_round_trip_through_files(box_views, tmp_path) -> None:  # type: ignore[no-untyped-def]
    mesh, views, to_world = box_views
    example = with_truth(observed_example(views[:2], SMALL), mesh, to_world, SMALL)
    write_example(tmp_path / "e.npz", example, {"part_id": "box"})
    back = read_example(tmp_path / "e.npz")
    assert back.meta["part_id"] == "box" and back.views == example.views
    assert np.array_equal(back.inputs, example.inputs) and back.target is not None
    assert np.array_equal(back.target, example.target)
    assert back.grid.grid_to_world(8) == pytest.approx(example.grid.grid_to_world(8))


def test_view_sets_spread_views() -> None:
    assert view_sets(8, 8, (2, 4, 8)) == [(i,) for i in range(8)] + [(0, 4), (0, 2, 4, 6),
                                                                     tuple(range(8))]
    assert view_sets(3, 3, (2, 4)) == [(0,), (1,), (2,), (0, 2)]


def test_carve_sees_nothing_without_views() -> None:
    grid = CubeGrid(np.eye(3), np.zeros(3), 1.0)
    assert not carve([], grid, 8).any()


def _states_iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def test_view_states_are_three_and_honest(box_views) -> None:  # type: ignore[no-untyped-def]
    """Seen free space never lies inside the solid, the seen surface lies on it, and what is
    behind the surface stays unknown (neither state)."""
    mesh, views, to_world = box_views
    example = with_truth(observed_example(views[:1], SMALL), mesh, to_world, SMALL)
    assert example.target is not None and example.inputs.shape == (1, 2, 16, 16, 16)
    n = SMALL.n_in
    states = view_states(views[0].evidence, views[0].points, example.grid, n)
    assert np.array_equal(states, example.inputs[0])
    surface, free = states[SURFACE], states[FREE]
    assert not (surface & free).any() and surface.any() and free.sum() > surface.sum()
    solid = truth_occupancy(mesh, to_world, example.grid, n)
    assert (free & solid).sum() <= 0.02 * solid.sum()
    unknown = ~(surface | free)
    hidden = solid & ~surface
    assert (unknown & hidden).sum() >= 0.9 * hidden.sum()  # the hidden back is unknown


def test_inputs_do_not_depend_on_how_many_pixels_a_voxel_catches() -> None:
    """The same view taken by a sensor with 64 times fewer pixels (80 x 60: a small part of an
    assembly catches about as few) gives nearly the same states in the same grid; the binned
    points alone lose far more."""
    mesh = _box(60, 40, 30)
    pose = _pose(20, (-30, -20, 0))
    grid, out = None, {}
    for width in (640, 80):
        views, _ = render_part_views(mesh, pose, [0], CaptureConfig(width=width,
                                                                    height=width * 3 // 4))
        grid = grid or observed_example(views, SMALL).grid
        out[width] = (view_states(views[0].evidence, views[0].points, grid, SMALL.n_in),
                      observed_occupancy(views[0].points, grid, SMALL.n_in), len(views[0].points))
    (fine, fine_pts, n_fine), (coarse, coarse_pts, n_coarse) = out[640], out[80]
    assert n_fine > 50 * n_coarse
    assert _states_iou(fine[FREE], coarse[FREE]) > 0.9
    surface_iou = _states_iou(fine[SURFACE], coarse[SURFACE])
    assert surface_iou > 0.6 and surface_iou > _states_iou(fine_pts, coarse_pts) + 0.05


def test_an_occluded_part_gets_room_where_its_neighbour_hides_it() -> None:
    """A box half hidden behind a nearer one: its silhouette side next to the occluder is
    found, the grid goes on into the hidden space there, and it holds more of the part."""
    from cadio.camera.render import PlacedPart, render_views
    from cadio.capture.examples import part_views

    back, front = _box(80, 30, 30), _box(50, 20, 80)
    parts = [PlacedPart(1, back, _pose(0, (-40, 40, 0)), part_id="back"),
             PlacedPart(2, front, _pose(0, (-55, -60, 0)), part_id="front")]
    frames = list(render_views(parts, CAPTURE, [0]))
    labels = [f.instance for f in frames]
    views = part_views(frames, labels, 1)  # type: ignore[arg-type]
    assert views and "left" in occluded_sides(views[0].evidence)
    assert "right" not in occluded_sides(views[0].evidence)
    scale = float(frames[0].meta["scale_m_per_mm"])
    to_world = np.diag([scale, scale, scale, 1.0]) @ parts[0].pose
    naive = place_grid(views[0].points, views[0].evidence.world_to_camera)
    example = with_truth(observed_example(views, SMALL), back, to_world, SMALL)
    assert example.grid.side > naive.side
    ref = replace(example, grid=naive)
    naive_cov = with_truth(ref, back, to_world, SMALL).coverage
    assert example.coverage > naive_cov + 0.1 and example.coverage > 0.85


def test_a_part_s_oracle_examples_share_their_projections_and_truth(box_views) -> None:  # type: ignore[no-untyped-def]
    """Built with the part's ``PartGrids``, every oracle-box example is what it is alone."""
    mesh, views, to_world = box_views
    grids = PartGrids()
    for seq in (views[:1], views[:2], views[1:2], views[:2]):
        shared = with_truth(oracle_example(seq, mesh, to_world, SMALL, grids), mesh, to_world,
                            SMALL, grids)
        alone = with_truth(oracle_example(seq, mesh, to_world, SMALL), mesh, to_world, SMALL)
        for field in ("inputs", "depth", "visible", "carve", "target"):
            assert np.array_equal(getattr(shared, field), getattr(alone, field)), field
    assert grids.oracle(mesh, to_world, SMALL.grid_margin) is shared.grid
