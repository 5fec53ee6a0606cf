"""Tests of cadio.capture.primitives: the geometric baseline on points sampled from real solids.

Solids are built with build123d and tessellated by the project's mesher; points are drawn on the
triangles by area (all around), or only where the surface faces a camera, with depth noise (a
partial scan), or as surface voxel centres of a 64^3 grid (a completed shape's staircase).
"""

from __future__ import annotations

import math

import build123d as bd
import numpy as np
import pytest

from cadio.cad import features as brep_features
from cadio.cad.tessellate import tessellate
from cadio.cad.voxels import voxelize
from cadio.capture.primitives import PrimitiveConfig, fit_features, relate_many, relate_points
from cadio.records import Relation
from cadio.tolerances import DEFAULT_TOLERANCES as TOL
from cadio.truth.relations import relate
from reports.metrics import surface_points

# Finer angular deflection than the default so that sampled cylinders are round to ~0.02 mm.
FINE = TOL.with_overrides({"mesh_angular_rad": 0.1})
UP, FRONT_VIEW, BACK_VIEW = (0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0)
N_POINTS = 600


def _surface(solid: bd.Shape, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n points (mm) drawn uniformly by area on the solid's mesh, and their outward normals."""
    mesh = tessellate(solid.wrapped, FINE)
    tri = mesh.vertices[mesh.triangles]  # (m, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(area), n, p=area / area.sum())
    u, v = rng.random((2, n))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[pick]
    points = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return points, cross[pick] / (2 * area[pick, None])


def sample(solid: bd.Shape, seed: int = 0) -> np.ndarray:
    return _surface(solid, N_POINTS, seed)[0]


def partial_scan(solid: bd.Shape, camera_dir: tuple[float, float, float],
                 sigma_mm: float = 0.1, seed: int = 0) -> np.ndarray:
    """The points a camera looking along ``camera_dir`` sees, with depth noise along its ray."""
    cam = np.asarray(camera_dir, dtype=float) / np.linalg.norm(camera_dir)
    points, normals = _surface(solid, 6 * N_POINTS, seed)
    seen = points[normals @ cam < -0.05]
    rng = np.random.default_rng(seed + 1)
    seen = seen[rng.choice(len(seen), min(N_POINTS, len(seen)), replace=False)]
    return seen + rng.normal(0.0, sigma_mm, (len(seen), 1)) * cam


def voxel_surface(solid: bd.Shape, seed: int = 0) -> np.ndarray:
    grid = voxelize(tessellate(solid.wrapped, FINE), 64)
    pts = surface_points(grid.occupancy, grid.voxel_size, grid.grid_to_part)
    return pts[np.random.default_rng(seed).choice(len(pts), N_POINTS, replace=False)]


def angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    """Angle between two undirected lines, degrees."""
    return math.degrees(math.atan2(np.linalg.norm(np.cross(u, v)), abs(float(np.dot(u, v)))))


def tube(x: float = 0.0) -> bd.Shape:
    """A tube (radii 10 and 6, 20 mm long) on a vertical axis through (x, 0), z in [15, 35]:
    standing on the shaft's end, its bore 1 mm off the shaft's side at the rim."""
    return bd.Pos(x, 0, 25) * (bd.Cylinder(10, 20) - bd.Cylinder(6, 20))


@pytest.fixture(scope="module")
def shaft() -> np.ndarray:
    """A shaft, radius 5 mm, z in [-15, 15] on the Z axis."""
    return sample(bd.Cylinder(5, 30))


@pytest.fixture(scope="module")
def plate() -> np.ndarray:
    """A 40 x 30 x 4 mm plate, z in [-2, 2]."""
    return sample(bd.Box(40, 30, 4))


# ---------------------------------------------------------------- known cases


def test_coaxial_shaft_and_tube_are_concentric(shaft: np.ndarray) -> None:
    upper = sample(tube(), seed=1)
    r = relate_points(upper, shaft, FRONT_VIEW)
    assert r[Relation.CONCENTRIC] and r[Relation.ABOVE] and not r[Relation.BELOW]
    assert not r.contact.measured  # estimated from the fitted features
    swapped = relate_points(shaft, upper, FRONT_VIEW)
    assert swapped[Relation.CONCENTRIC] and swapped[Relation.BELOW]


def test_offset_axes_are_not_concentric(shaft: np.ndarray) -> None:
    r = relate_points(sample(tube(x=5.0), seed=1), shaft, FRONT_VIEW)
    assert not r[Relation.CONCENTRIC]


def test_stacked_plates_are_parallel_and_above(plate: np.ndarray) -> None:
    upper = sample(bd.Pos(0, 0, 8) * bd.Box(40, 30, 4), seed=1)
    r = relate_points(upper, plate, FRONT_VIEW)
    assert r[Relation.ABOVE] and r[Relation.PARALLEL]
    assert not r[Relation.COINCIDENT] and not r[Relation.PERPENDICULAR]
    assert r.contact.coincident_gap_mm == pytest.approx(4.0, abs=0.2)  # bottom to top
    below = relate_points(plate, upper, FRONT_VIEW)
    assert below[Relation.BELOW] and below[Relation.PARALLEL]


def test_plate_on_its_edge_is_perpendicular(plate: np.ndarray) -> None:
    standing = sample(bd.Pos(40, 0, 0) * bd.Box(4, 30, 40), seed=2)
    r = relate_points(standing, plate, FRONT_VIEW)
    assert r[Relation.PERPENDICULAR] and not r[Relation.PARALLEL]
    assert r[Relation.RIGHT]  # +X of the plate, observer looking along +Y


def test_left_and_right_follow_the_observer() -> None:
    a = sample(bd.Pos(-30, 0, 0) * bd.Box(20, 20, 20), seed=3)
    b = sample(bd.Pos(30, 0, 0) * bd.Box(20, 20, 20), seed=4)
    front, back = relate_points(a, b, FRONT_VIEW), relate_points(a, b, BACK_VIEW)
    assert front[Relation.LEFT] and not front[Relation.RIGHT]
    assert back[Relation.RIGHT] and not back[Relation.LEFT]


def test_principal_plane_matches_the_brep() -> None:
    solid = bd.Rot(20, 35, 10) * bd.Box(40, 30, 4)
    truth = brep_features.extract_features(solid.wrapped)
    fitted = fit_features(sample(solid))
    assert truth.principal_plane is not None and fitted.principal_plane is not None
    assert angle_deg(fitted.principal_plane, truth.principal_plane) <= 1.0
    assert not fitted.principal_plane_tie
    assert fitted.principal_axis is None  # box edges are not taken for cylinders


def test_tie_rule_is_the_brep_rule() -> None:
    from cadio.records import principal_choice

    assert principal_choice([5.0, 10.0, 9.95]) == (1, True)  # within 1%: a tie, the first kept
    assert principal_choice([5.0, 10.0, 9.8]) == (1, False)
    assert principal_choice([]) == (None, False)


# ---------------------------------------------------------------- partial and completed inputs


def test_partial_scan_from_above_keeps_the_principal_plane() -> None:
    solid = bd.Box(40, 30, 4)
    pts = partial_scan(solid, camera_dir=(0.3, 0.4, -1.0))
    f = fit_features(pts)
    assert f.principal_plane is not None
    assert angle_deg(f.principal_plane, np.array(UP)) <= 1.0


def test_partial_scan_of_a_shaft_finds_its_axis() -> None:
    f = fit_features(partial_scan(bd.Cylinder(5, 30), camera_dir=(0.0, 1.0, -0.3)))
    assert f.principal_axis is not None
    assert angle_deg(f.principal_axis.direction, np.array(UP)) <= 1.0
    assert f.principal_axis.radii[0] == pytest.approx(5.0, abs=0.2)


def test_voxel_staircase_keeps_the_principal_plane() -> None:
    solid = bd.Rot(0, 0, 30) * bd.Box(40, 30, 4)
    f = fit_features(voxel_surface(solid))
    assert f.principal_plane is not None
    assert angle_deg(f.principal_plane, np.array(UP)) <= 1.0


# ---------------------------------------------------------------- records, determinism, degenerate


def test_features_follow_the_record_conventions(plate: np.ndarray) -> None:
    f = fit_features(plate)
    assert f.centroid == pytest.approx(np.zeros(3), abs=0.2)  # hull centroid: the box's
    assert np.all(f.bbox_min <= plate.min(axis=0)) and np.all(f.bbox_max >= plate.max(axis=0))
    assert f.volume == pytest.approx(40 * 30 * 4, rel=0.1)
    top = f.planes[0]
    # Hull areas of the inliers: points on the edges, whose normals blend two faces, are none.
    assert top.normal[2] > 0 and top.area == pytest.approx(2 * 40 * 30, rel=0.2)
    assert sorted(zip(top.offsets, top.outward, strict=True)) == [
        (pytest.approx(-2.0, abs=0.05), -1), (pytest.approx(2.0, abs=0.05), 1)]
    ids = [i for g in f.planes for i in g.face_ids] + [i for a in f.axes for i in a.face_ids]
    assert sorted(ids) == list(range(f.n_faces))


def test_same_seed_same_features(shaft: np.ndarray) -> None:
    a, b = fit_features(shaft), fit_features(shaft)
    assert a.to_dict() == b.to_dict()
    other = fit_features(shaft, PrimitiveConfig(seed=7))
    assert other.principal_axis is not None
    assert angle_deg(other.principal_axis.direction, np.array(UP)) <= TOL.coaxial_deg


@pytest.mark.parametrize("n", [0, 1, 2])
def test_fewer_than_three_points_is_refused(n: int) -> None:
    with pytest.raises(ValueError, match="at least 3 points"):
        fit_features(np.zeros((n, 3)))


def test_bad_arrays_are_refused() -> None:
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        fit_features(np.zeros((10, 2)))
    pts = np.zeros((10, 3))
    pts[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fit_features(pts)


@pytest.mark.parametrize("noise", [0.0, 1e-3])
def test_line_of_points_has_no_planes(noise: float) -> None:
    rng = np.random.default_rng(0)
    pts = np.outer(np.linspace(0, 50, 200), [1.0, 2.0, 0.5]) + rng.normal(0, noise, (200, 3))
    f = fit_features(pts)
    assert f.planes == () and f.principal_plane is None and f.principal_axis is None
    assert f.volume == 0.0 or noise > 0


def test_coincident_points_have_no_features() -> None:
    f = fit_features(np.ones((5, 3)))
    assert f.planes == () and f.axes == () and f.volume == 0.0
    assert f.centroid == pytest.approx(np.ones(3))


def test_flat_cloud_has_its_plane() -> None:
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-20, 20, (300, 2)), np.full(300, 3.0)])
    f = fit_features(pts)
    assert f.volume == 0.0 and f.centroid == pytest.approx(pts.mean(axis=0))
    assert f.principal_plane == pytest.approx(np.array(UP), abs=1e-9)
    assert f.planes[0].offsets == (pytest.approx(3.0),)


def test_relate_many_matches_relate_points(shaft: np.ndarray, plate: np.ndarray) -> None:
    upper = sample(tube(), seed=1)
    clouds = [shaft, plate, upper]
    pairs = [(2, 0), (0, 2), (1, 0)]
    views = [FRONT_VIEW, BACK_VIEW, FRONT_VIEW]
    table = relate_many(clouds, pairs, views)
    assert table.shape == (3, 10) and table.dtype == bool
    for row, ((i, j), view) in zip(table, zip(pairs, views, strict=True), strict=True):
        assert tuple(row) == relate(fit_features(clouds[i]), fit_features(clouds[j]), view).truth
    with pytest.raises(ValueError, match="pair indices"):
        relate_many(clouds, [(0, 3)], FRONT_VIEW)
