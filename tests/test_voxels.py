"""Tests of cadio.cad.voxels: grid placement, solid occupancy, point binning, IoU."""

from __future__ import annotations

from pathlib import Path

import build123d as bd
import numpy as np
import open3d as o3d
import pytest

from cadio.cad.step import read_step
from cadio.cad.tessellate import brep_volume, tessellate
from cadio.cad.voxels import (
    grid_transform,
    iou,
    occupancy_in,
    points_to_grid,
    voxel_centres,
    voxelize,
    voxelize_sizes,
)
from cadio.records import Mesh, VoxelGrid
from cadio.workspace import read_voxels, write_voxels

NUT = "fasteners/kcl_hex-nut.step"


def voxel_volume(grid: VoxelGrid) -> float:
    return float(np.count_nonzero(grid.occupancy)) * grid.voxel_size**3


@pytest.fixture(scope="module")
def nut_grids(step_solids) -> tuple[float, VoxelGrid, VoxelGrid]:
    """(B-rep volume, 64^3 grid, 256^3 grid) of a real nut: the only 256^3 voxelization."""
    solid = step_solids(NUT)[0]
    mesh = tessellate(solid)
    return brep_volume(solid), voxelize(mesh, 64), voxelize(mesh, 256)


def test_grid_transform_is_a_centred_unstretched_cube() -> None:
    t = grid_transform(np.array([0.0, -10.0, 4.0]), np.array([20.0, 10.0, 6.0]), n=10, margin=0.1)
    size = 20.0 * 1.1 / 10
    np.testing.assert_allclose(np.diag(t), [size, size, size, 1.0])
    centres = voxel_centres(t, 10)
    assert centres.shape == (10, 10, 10, 3)
    np.testing.assert_allclose((centres[0, 0, 0] + centres[-1, -1, -1]) / 2, [10, 0, 5], atol=1e-5)
    np.testing.assert_allclose(centres[1, 2, 3] - centres[0, 0, 0], [size, 2 * size, 3 * size],
                               rtol=1e-5)
    with pytest.raises(ValueError):
        grid_transform(np.zeros(3), np.zeros(3), 8)
    with pytest.raises(ValueError):
        grid_transform(np.zeros(3), np.ones(3), 0)


def test_box_occupancy_matches_volume_and_position() -> None:
    box = bd.Pos(40, -3, 7) * bd.Box(30, 10, 20)
    grid = voxelize(tessellate(box.wrapped), 64, margin=0.0)
    assert grid.n == 64 and grid.occupancy.dtype == np.bool_
    assert voxel_volume(grid) == pytest.approx(6000.0, rel=0.03)
    centres = voxel_centres(grid.grid_to_part, 64)[grid.occupancy]
    np.testing.assert_allclose(centres.mean(axis=0), [40, -3, 7], atol=0.3)


def test_iou() -> None:
    a = np.zeros((4, 4, 4), dtype=bool)
    b = a.copy()
    assert iou(a, b) == 1.0
    a[0, 0, :2] = True
    b[0, 0, 1:3] = True
    assert iou(a, a) == 1.0
    assert iou(a, b) == pytest.approx(1 / 3)
    assert iou(a, ~a) == 0.0
    with pytest.raises(ValueError):
        iou(a, np.zeros((2, 2, 2), dtype=bool))


def test_points_to_grid_inverts_voxel_centres() -> None:
    t = grid_transform(np.array([-5.0, 0.0, 0.0]), np.array([5.0, 8.0, 3.0]), n=16)
    rng = np.random.default_rng(0)
    truth = rng.random((16, 16, 16)) < 0.1
    centres = voxel_centres(t, 16)[truth].astype(np.float64)
    jitter = rng.uniform(-0.49, 0.49, centres.shape) * t[0, 0]
    assert np.array_equal(points_to_grid(centres + jitter, t, 16), truth)
    far = np.array([[1e4, 0.0, 0.0], [-1e4, 0.0, 0.0]])
    assert not points_to_grid(far, t, 16).any()
    with pytest.raises(ValueError):
        points_to_grid(np.zeros((3, 2)), t, 16)


@pytest.mark.shared
def test_real_part_voxel_volume_matches_brep(nut_grids) -> None:
    exact, g64, g256 = nut_grids
    assert g64.occupancy.shape == (64, 64, 64) and g256.occupancy.shape == (256, 256, 256)
    assert voxel_volume(g64) == pytest.approx(exact, rel=0.03)
    assert voxel_volume(g256) == pytest.approx(exact, rel=0.02)
    assert iou(g64.occupancy, g64.occupancy) == 1.0
    assert iou(g256.occupancy, g256.occupancy) == 1.0


@pytest.mark.shared
def test_mesh_points_fall_on_the_same_parts_grid(nut_grids, step_solids) -> None:
    """Surface points binned on the truth grid land on or next to occupied voxels."""
    _, g64, _ = nut_grids
    mesh = tessellate(step_solids(NUT)[0])
    hits = points_to_grid(mesh.vertices, g64.grid_to_part, g64.n)
    grown = g64.occupancy.copy()
    for axis in range(3):
        for shift in (-1, 1):
            grown |= np.roll(g64.occupancy, shift, axis=axis)
    assert hits.any() and not (hits & ~grown).any()


@pytest.mark.shared
def test_voxels_round_trip_through_workspace(nut_grids, tmp_path: Path) -> None:
    _, g64, g256 = nut_grids
    for grid in (g64, g256):
        path = tmp_path / f"part@{grid.n}.npz"
        write_voxels(path, grid)
        back = read_voxels(path)
        assert np.array_equal(back.occupancy, grid.occupancy)
        np.testing.assert_array_equal(back.grid_to_part, grid.grid_to_part)


def asked_everywhere(mesh: Mesh, n: int, t: np.ndarray | None = None) -> np.ndarray:
    """Occupancy from open3d at every voxel centre: what the skipped voxels must agree with."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor.from_numpy(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor.from_numpy(mesh.triangles.astype(np.uint32)))
    if t is None:
        t = grid_transform(mesh.vertices.min(axis=0), mesh.vertices.max(axis=0), n)
    return scene.compute_occupancy(o3d.core.Tensor.from_numpy(voxel_centres(t, n))).numpy() > 0


SHAPES = [
    lambda: bd.Box(40, 30, 2),  # a flat plate: most of its cube is provably empty
    lambda: bd.Pos(500, -80, 20) * bd.Rot(10, 60, 30) * (bd.Cylinder(3, 50) + bd.Sphere(6)),
    lambda: bd.fillet(bd.Box(20, 20, 20).edges(), 2) - bd.Sphere(6),  # a hollow
]


@pytest.mark.parametrize("make", SHAPES)
def test_line_parity_agrees_with_open3d_at_every_centre(make) -> None:  # type: ignore[no-untyped-def]
    """On a closed mesh, the parity along grid lines (and the skipped sure misses) give open3d's
    answer at every voxel centre, at odd and even sizes (centres on symmetry planes and edges)."""
    mesh = tessellate(make().wrapped)
    for n, grid in zip((16, 33, 64), voxelize_sizes(mesh, (16, 33, 64)), strict=True):
        assert np.array_equal(grid.occupancy, asked_everywhere(mesh, n))


@pytest.mark.parametrize("make", SHAPES)
def test_a_holed_mesh_errs_less_than_one_ray_per_voxel(make) -> None:  # type: ignore[no-untyped-def]
    """Five triangles removed: a line through a hole is unsure (odd crossings) or outvoted by the
    other axis; the grid stays closer to the closed mesh's than open3d's ray from each centre."""
    mesh = tessellate(make().wrapped)
    holed = Mesh(vertices=mesh.vertices, triangles=mesh.triangles[5:])
    for n in (16, 33, 64):
        truth = voxelize(mesh, n).occupancy
        t = grid_transform(mesh.vertices.min(axis=0), mesh.vertices.max(axis=0), n)
        ours = occupancy_in(holed, t, n)
        one_ray = asked_everywhere(holed, n, t)
        assert np.count_nonzero(ours != truth) <= np.count_nonzero(one_ray != truth)


def test_occupancy_on_a_turned_grid_skips_only_empty_voxels() -> None:
    """A grid placed by a camera's view is rotated and offset: the shortcut must still hold."""
    mesh = tessellate((bd.Box(30, 12, 8) - bd.Cylinder(3, 8)).wrapped)
    turn = np.eye(4)
    turn[:3, :3] = 1.2 * np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    turn[:3, 3] = np.array([1.0, -2.0, 0.5]) - turn[:3, :3] @ np.full(3, 16.0)  # near the middle
    grid = occupancy_in(mesh, turn, 33)
    assert grid.any() and not grid.all()
    assert np.array_equal(grid, asked_everywhere(mesh, 33, turn))


def test_where_one_ray_per_voxel_errs_on_a_real_gear_a_vote_sides_with_the_lines(
        shared_step_dir: Path) -> None:
    """On a real spur gear's mesh, open3d's single ray from a voxel centre meets triangle edges
    and miscounts some voxels (17 at 64^3); seven rays in random directions side with the
    lines' parity on every voxel where the two differ."""
    differing = 0
    for solid in read_step(shared_step_dir / "linear-rotary-motion/kcl_spur-gear.step"):
        mesh = tessellate(solid.shape)
        grid = voxelize(mesh, 64)
        differ = np.nonzero(grid.occupancy != asked_everywhere(mesh, 64))
        differing += len(differ[0])
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor.from_numpy(mesh.vertices.astype(np.float32)),
                            o3d.core.Tensor.from_numpy(mesh.triangles.astype(np.uint32)))
        centres = voxel_centres(grid.grid_to_part, 64)[differ]
        vote = scene.compute_occupancy(o3d.core.Tensor.from_numpy(centres), nsamples=7).numpy()
        assert np.array_equal(vote > 0, grid.occupancy[differ])
    assert differing > 0
