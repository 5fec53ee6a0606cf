"""The inspection's pieces on exact geometry: symmetries and pose errors, what a fit's points
constrain, a mate's residuals and status, registration from a seed and from nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cadio.inspect.asbuilt import (
    BROKEN,
    HOLDS,
    NOT_INSPECTABLE,
    NOT_OBSERVABLE,
    Limits,
    PartAsBuilt,
    mate_as_built,
    verdict,
)
from cadio.inspect.register import RegisterConfig, global_search, refine
from cadio.inspect.scan import Scan, consistency
from cadio.inspect.surface import Camera, part_surface, visible
from cadio.inspect.symmetry import Symmetry, pose_error, symmetry_of
from cadio.inspect.uncertainty import pose_uncertainty
from cadio.records import CameraIntrinsics, Mesh


def _box_mesh(sx: float, sy: float, sz: float) -> Mesh:
    """A closed box centred on the origin, outward triangles (mm)."""
    v = np.array([[x, y, z] for x in (-sx / 2, sx / 2) for y in (-sy / 2, sy / 2)
                  for z in (-sz / 2, sz / 2)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4),
             (1, 5, 7, 3)]
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return Mesh(v.astype(np.float64), np.array(tris, dtype=np.int64))


def _cylinder_mesh(radius: float, height: float, n: int = 96) -> Mesh:
    """A closed cylinder on Z centred on the origin, outward triangles (mm)."""
    a = np.linspace(0, 2 * math.pi, n, endpoint=False)
    ring = np.column_stack([radius * np.cos(a), radius * np.sin(a)])
    v = np.vstack([np.column_stack([ring, np.full(n, -height / 2)]),
                   np.column_stack([ring, np.full(n, height / 2)]),
                   [[0, 0, -height / 2], [0, 0, height / 2]]])
    tris = []
    for i in range(n):
        j = (i + 1) % n
        tris += [(i, j, n + j), (i, n + j, n + i), (2 * n, j, i), (2 * n + 1, n + i, n + j)]
    return Mesh(v, np.array(tris, dtype=np.int64))


def _l_mesh() -> Mesh:
    """An L of two boxes, its arms 30 and 20 mm long (no symmetry but a mirror, which is no
    motion)."""
    a, b = _box_mesh(40, 10, 10), _box_mesh(10, 20, 10)
    va = a.vertices
    vb = b.vertices + np.array([15.0, 15.0, 0.0])
    return Mesh(np.vstack([va, vb]), np.vstack([a.triangles, b.triangles + len(va)]))


def _ball_mesh(radius: float, n: int = 48) -> Mesh:
    """A closed UV sphere centred on the origin, outward triangles (mm)."""
    polar = np.linspace(0, math.pi, n // 2 + 1)[1:-1]
    around = np.linspace(0, 2 * math.pi, n, endpoint=False)
    rings = [radius * np.column_stack([np.sin(p) * np.cos(around), np.sin(p) * np.sin(around),
                                       np.full(n, np.cos(p))]) for p in polar]
    v = np.vstack([*rings, [[0, 0, radius], [0, 0, -radius]]])
    top, bottom, last = len(v) - 2, len(v) - 1, (len(polar) - 1) * n
    tris = []
    for i in range(n):
        j = (i + 1) % n
        tris += [(top, i, j), (bottom, last + j, last + i)]
        for r in range(len(polar) - 1):
            a, b = r * n, (r + 1) * n
            tris += [(a + i, b + i, b + j), (a + i, b + j, a + j)]
    return Mesh(v, np.array(tris, dtype=np.int64))


def _pose(deg: float, axis: tuple[float, float, float], shift: tuple[float, float, float]
          ) -> np.ndarray:
    k = np.array(axis, dtype=np.float64) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    t = math.radians(deg)
    out = np.eye(4)
    out[:3, :3] = np.eye(3) + math.sin(t) * kx + (1 - math.cos(t)) * kx @ kx
    out[:3, 3] = shift
    return out


def _camera(at_mm: tuple[float, float, float] = (0.0, -300.0, 200.0)) -> Camera:
    """A 640 x 480 camera looking at the origin from ``at_mm``."""
    eye = np.array(at_mm, dtype=np.float64)
    forward = -eye / np.linalg.norm(eye)
    right = np.cross(forward, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot = np.vstack([right, down, forward])
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ eye
    return Camera(CameraIntrinsics(width=640, height=480, fx=600.0, fy=600.0, cx=320.0,
                                   cy=240.0), w2c)


# ---------------------------------------------------------------- symmetry


def test_a_cylinder_is_revolved_and_flips_a_box_turns_half_an_l_not_at_all() -> None:
    cylinder = symmetry_of(part_surface("c", _cylinder_mesh(10, 40)).samples)
    assert cylinder.continuous and cylinder.axis is not None
    assert abs(abs(cylinder.axis[2]) - 1) < 1e-3 and cylinder.flip is not None
    box = symmetry_of(part_surface("b", _box_mesh(60, 30, 10)).samples)
    assert box.order == 2 and box.flip is not None
    ell = symmetry_of(part_surface("l", _l_mesh()).samples)
    assert ell.axis is None and ell.flip is None


def test_a_pose_error_is_the_least_over_the_part_s_symmetries() -> None:
    surface = part_surface("c", _cylinder_mesh(10, 40))
    sym = symmetry_of(surface.samples)
    truth = _pose(20, (1, 0, 0), (5, 6, 7))
    turned = truth @ _pose(73, (0, 0, 1), (0, 0, 0))  # a turn about its own axis
    mm, deg = pose_error(turned, truth, sym)
    assert mm < 0.05 and deg < 0.1  # (the axis is fitted to a 96-sided prism's samples)
    none = Symmetry(tuple(surface.centre))  # type: ignore[arg-type]
    assert pose_error(turned, truth, none)[1] == pytest.approx(73, abs=0.1)
    shifted = _pose(0, (0, 0, 1), (0.3, 0, 0)) @ truth
    mm, deg = pose_error(shifted, truth, sym)
    assert mm == pytest.approx(0.3, abs=0.02) and deg < 0.01


def test_a_ball_turned_any_way_is_the_same_ball_and_a_shaft_is_not() -> None:
    ball = symmetry_of(part_surface("s", _ball_mesh(6)).samples)
    shaft = symmetry_of(part_surface("c", _cylinder_mesh(10, 40)).samples)
    assert ball.spherical and ball.continuous and not shaft.spherical
    truth = _pose(20, (1, 0, 0), (5, 6, 7))
    tumbled = truth @ _pose(67, (1, 2, 0), (0, 0, 0)) @ _pose(0, (0, 0, 1), (0.2, 0, 0))
    mm, deg = pose_error(tumbled, truth, ball)
    assert deg == 0.0 and mm == pytest.approx(0.2, abs=0.02)
    assert pose_error(tumbled, truth, shaft)[1] > 60
    assert Symmetry.from_dict(ball.to_dict()) == ball


def test_a_symmetry_survives_its_record() -> None:
    sym = symmetry_of(part_surface("b", _box_mesh(60, 30, 10)).samples)
    assert Symmetry.from_dict(sym.to_dict()) == sym


# ---------------------------------------------------------------- uncertainty


def test_a_plate_seen_face_on_does_not_constrain_its_slide_in_its_plane() -> None:
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-30, 30, 500), rng.uniform(-30, 30, 500),
                              np.zeros(500)])
    normals = np.tile([0, 0, 1.0], (500, 1))
    jac = np.hstack([np.cross(points, normals), normals])
    u = pose_uncertainty(jac.T @ jac, 0.5, 500, np.zeros(3), 30.0)
    along_normal = u.sigma_along(np.array([0, 0, 0, 0, 0, 1.0]))
    assert 0 < along_normal < 0.5
    assert math.isinf(u.sigma_along(np.array([0, 0, 0, 1.0, 0, 0])))  # slide in the plane
    assert math.isinf(u.sigma_along(np.array([0, 0, 1.0, 0, 0, 0])))  # turn about the normal
    # more noise, more uncertainty
    noisier = pose_uncertainty(jac.T @ jac, 1.0, 500, np.zeros(3), 30.0)
    assert noisier.sigma_along(np.array([0, 0, 0, 0, 0, 1.0])) > along_normal


# ---------------------------------------------------------------- a mate as built


def _firm(index: int, pose: np.ndarray, sigma_mm: float = 0.01) -> PartAsBuilt:
    """A part seen all round: every direction observed, ``sigma_mm`` of error."""
    u = pose_uncertainty(np.eye(6) * (1e4 / 25), sigma_mm * 10, 1, pose[:3, 3], 5.0, 1.0)
    return PartAsBuilt(index, pose, u)


COINCIDENT = {"index_a": 0, "index_b": 1, "face_a": 3, "face_b": 7, "relation": "coincident",
              "level": "face", "axis": [0, 0, 1.0], "origin": [0, 0, 10.0]}
CONCENTRIC = {**COINCIDENT, "relation": "concentric", "axis": [0, 0, 1.0], "origin": [0, 0, 0]}


def test_a_mate_holds_as_designed_and_wherever_the_whole_assembly_stands() -> None:
    design = {0: _pose(0, (0, 0, 1), (0, 0, 15)), 1: np.eye(4)}
    moved = _pose(30, (1, 1, 0), (100, -50, 20))  # the whole assembly elsewhere
    parts = {i: _firm(i, moved @ d) for i, d in design.items()}
    for row in (COINCIDENT, CONCENTRIC):
        mate = mate_as_built(row, parts, design, Limits.of())
        assert mate.status == HOLDS, mate
        assert all(r.value < 1e-6 for r in mate.residuals)


def test_a_part_lifted_off_its_face_breaks_the_coincident_mate_not_a_slide() -> None:
    design = {0: _pose(0, (0, 0, 1), (0, 0, 15)), 1: np.eye(4)}
    lifted = {0: _firm(0, _pose(0, (0, 0, 1), (0, 0, 1.0)) @ design[0]), 1: _firm(1, np.eye(4))}
    mate = mate_as_built(COINCIDENT, lifted, design, Limits.of())
    assert mate.status == BROKEN
    assert dict((r.name, r.value) for r in mate.residuals)["plane_offset_mm"] == \
        pytest.approx(1.0)
    slid = {0: _firm(0, _pose(0, (0, 0, 1), (3.0, 0, 0)) @ design[0]), 1: _firm(1, np.eye(4))}
    assert mate_as_built(COINCIDENT, slid, design, Limits.of()).status == HOLDS
    # the same slide moves a concentric mate's axis off
    off_axis = mate_as_built(CONCENTRIC, slid, design, Limits.of())
    assert off_axis.status == BROKEN
    assert off_axis.row()["axis_distance_mm"] == pytest.approx(3.0)
    assert off_axis.row()["axis_distance_mm_threshold"] < 3.0


def test_a_pose_s_uncertainty_widens_the_threshold() -> None:
    design = {0: _pose(0, (0, 0, 1), (0, 0, 15)), 1: np.eye(4)}
    lift = _pose(0, (0, 0, 1), (0, 0, 1.0)) @ design[0]
    sure = mate_as_built(COINCIDENT, {0: _firm(0, lift), 1: _firm(1, np.eye(4))}, design,
                         Limits.of())
    unsure = mate_as_built(COINCIDENT, {0: _firm(0, lift, 0.5), 1: _firm(1, np.eye(4), 0.5)},
                           design, Limits.of())
    assert sure.status == BROKEN and unsure.status == HOLDS
    assert unsure.row()["plane_offset_mm_threshold"] > 1.0


def test_an_unconstrained_direction_is_not_observable_never_a_pass() -> None:
    design = {0: _pose(0, (0, 0, 1), (0, 0, 15)), 1: np.eye(4)}
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-30, 30, 400), rng.uniform(-30, 30, 400),
                              np.zeros(400)])
    side = np.tile([1.0, 0, 0], (400, 1))  # a's points all face X: its Z is not seen
    jac = np.hstack([np.cross(points, side), side])
    blind = PartAsBuilt(0, design[0], pose_uncertainty(jac.T @ jac, 0.1, 400, np.zeros(3),
                                                       30.0))
    mate = mate_as_built(COINCIDENT, {0: blind, 1: _firm(1, np.eye(4))}, design, Limits.of())
    assert mate.status == NOT_OBSERVABLE


def test_a_missing_part_breaks_its_mates_and_a_hidden_one_is_not_inspectable() -> None:
    design = {0: np.eye(4), 1: np.eye(4)}
    firm = _firm(1, np.eye(4))
    missing = mate_as_built(COINCIDENT, {0: PartAsBuilt(0, None, None, "missing"), 1: firm},
                            design, Limits.of())
    hidden = mate_as_built(COINCIDENT, {0: PartAsBuilt(0, None, None, "too little of it "
                                                       "visible"), 1: firm}, design,
                           Limits.of())
    assert missing.status == BROKEN and hidden.status == NOT_INSPECTABLE
    assert verdict([missing, hidden]) == "1 mate broken"
    assert verdict([hidden]) == NOT_INSPECTABLE


# ---------------------------------------------------------------- registration


def _seen(surface: object, pose: np.ndarray, cameras: list[Camera]) -> np.ndarray:
    points, _ = visible(surface, pose, cameras)  # type: ignore[arg-type]
    return points


def test_what_a_camera_sees_is_cast_only_within_the_part_s_bounding_cone() -> None:
    cameras = [_camera(), _camera((250.0, 150.0, 200.0)), _camera((-40.0, -90.0, 420.0))]
    for mesh in (_l_mesh(), _cylinder_mesh(4, 90), _box_mesh(60, 30, 10)):
        for deg, axis, shift in ((0, (0, 0, 1), (0, 0, 0)), (70, (1, 2, 0.5), (30, -20, 10)),
                                 (140, (0, 1, 1), (-60, 40, -25))):
            pose = _pose(deg, axis, shift)
            coned = part_surface("p", mesh)
            whole = part_surface("p", mesh)
            whole.__dict__["radius"] = 1e9  # a cone wider than the window: every pixel cast
            assert coned.radius < 0.6 * coned.diameter
            for stride in (1, 3):
                a, na = visible(coned, pose, cameras, stride)
                b, nb = visible(whole, pose, cameras, stride)
                assert len(a) > 50
                assert np.array_equal(a, b) and np.array_equal(na, nb)


def test_what_a_camera_sees_is_cast_only_where_a_ray_meets_the_part_s_box() -> None:
    """A ray that misses the part's box is not cast: what the cameras see is what casting
    every ray of the cone sees, for a long part seen side on and end on too."""
    cameras = [_camera(), _camera((250.0, 150.0, 200.0)), _camera((-40.0, -90.0, 420.0))]
    for mesh in (_l_mesh(), _cylinder_mesh(4, 90), _box_mesh(60, 30, 10)):
        for deg, axis, shift in ((0, (0, 0, 1), (0, 0, 0)), (90, (1, 0, 0), (0, 0, 0)),
                                 (70, (1, 2, 0.5), (30, -20, 10))):
            pose = _pose(deg, axis, shift)
            boxed = part_surface("p", mesh)
            whole = part_surface("p", mesh)
            whole.__dict__["box"] = (np.full(3, -1e9), np.full(3, 1e9))  # every ray meets it
            for stride in (1, 3):
                a, na = visible(boxed, pose, cameras, stride)
                b, nb = visible(whole, pose, cameras, stride)
                assert len(a) > 50
                assert np.array_equal(a, b) and np.array_equal(na, nb)


def test_registration_s_nearest_points_are_scipy_s() -> None:
    from pykdtree.kdtree import KDTree
    from scipy.spatial import cKDTree

    surface = part_surface("l", _l_mesh())
    seen = _seen(surface, _pose(40, (1, 1, 0), (3, -2, 1)), [_camera()])
    rng = np.random.default_rng(0)
    for model, reach in ((surface.samples, 8.0), (seen, 3.0)):
        scan = seen + rng.normal(0.0, 1.5, seen.shape)
        ours, theirs = KDTree(model).query(scan, distance_upper_bound=reach), \
            cKDTree(model).query(scan, distance_upper_bound=reach)
        near = np.isfinite(theirs[0])
        assert 0.2 < near.mean() < 1.0
        assert np.array_equal(np.isfinite(ours[0]), near)
        assert np.array_equal(ours[0][near], theirs[0][near])
        assert np.array_equal(ours[1][near].astype(np.int64), theirs[1][near])


def test_refine_brings_a_part_back_from_a_few_millimetres_and_degrees() -> None:
    surface = part_surface("l", _l_mesh())
    cameras = [_camera(), _camera((250.0, 150.0, 200.0))]
    truth = _pose(15, (0, 1, 1), (4, -3, 2))
    scan = _seen(surface, truth, cameras)
    start = _pose(3, (1, 0, 0), (1.5, -1.0, 1.0)) @ truth
    fit = refine(surface, scan, start, cameras)
    mm, deg = pose_error(fit.pose, truth, Symmetry(tuple(surface.centre)))  # type: ignore[arg-type]
    assert mm < 0.05 and deg < 0.05
    assert fit.fitness > 0.95 and fit.coverage > 0.9


def test_a_near_view_weighs_in_the_fit_by_its_depth_s_inverse_variance() -> None:
    """An L seen from 0.3 m and from 0.6 m, 150 points of each view off by the D435's noise at
    its distance (independent, seeded): weighed by the inverse variance ``Scan.sigma`` gives,
    the fits land nearer the truth than with every point alike."""
    from cadio.camera.noise import D435

    surface = part_surface("l", _l_mesh())
    truth = _pose(15, (0, 1, 1), (4, -3, 2))
    cameras = [_camera((0.0, -240.0, 180.0)), _camera((350.0, 300.0, 350.0))]
    errors: dict[bool, list[float]] = {True: [], False: []}
    for seed in range(6):
        rng = np.random.default_rng(seed)
        views = [rng.permutation(_seen(surface, truth, [cam]))[:150] for cam in cameras]
        sigma = [D435.depth_sigma_m(np.linalg.norm(v - cam.centre, axis=1) / 1000) * 1000
                 for v, cam in zip(views, cameras, strict=True)]
        assert 2.5 < float(np.median(sigma[1]) / np.median(sigma[0])) < 3.5  # variance 10x
        scan = np.vstack([v + rng.normal(0.0, 1.0, v.shape) * s[:, None]
                          for v, s in zip(views, sigma, strict=True)])
        start = _pose(2, (1, 0, 0), (1.0, -0.5, 0.5)) @ truth
        for weighted in (True, False):
            fit = refine(surface, scan, start, cameras,
                         sigma=np.concatenate(sigma) if weighted else None)
            _, deg = pose_error(fit.pose, truth,
                                 Symmetry(tuple(surface.centre)))  # type: ignore[arg-type]
            errors[weighted].append(deg)
    assert np.mean(errors[True]) < 0.7 * np.mean(errors[False]), errors


def test_the_search_s_coarse_steps_land_on_a_noise_free_part_from_ten_degrees_off() -> None:
    """Each step is taken where the last left the part: composed in the other order, the
    candidate's pose drifts from the one its steps converged to (0.35 mm and 0.45 degrees
    here)."""
    from cadio.inspect.register import coarse_scores

    surface = part_surface("l", _l_mesh())
    truth = _pose(15, (0, 1, 1), (4, -3, 2))
    scan = _seen(surface, truth, [_camera(), _camera((250.0, 150.0, 200.0))])
    start = _pose(10, (1, 0.3, 0), (4, -2, 1.3)) @ truth
    (_, pose), = coarse_scores(surface, scan, [start], RegisterConfig(coarse_iterations=10,
                                                                      coarse_points=2000))
    mm, deg = pose_error(pose, truth, Symmetry(tuple(surface.centre)))  # type: ignore[arg-type]
    assert mm < 0.01 and deg < 0.01, (mm, deg)


def test_each_step_icp_keeps_lowers_the_robust_cost_of_the_points_it_paired() -> None:
    """A nut (a hexagonal prism) seen by a D435 at 0.66 m, refined from where it stands: from
    the pose ICP returns after k steps to the one after k + 1, the robust cost of the points
    paired at the first never rises where each step is checked. Unchecked, plain Gauss-Newton
    steps under the sensor's correlated noise raise it; composed in the wrong order, the pose
    returned is not the one whose cost was checked."""
    from dataclasses import replace
    from itertools import pairwise

    from pykdtree.kdtree import KDTree

    from cadio.camera.noise import D435
    from cadio.camera.render import CaptureConfig, PlacedPart, render_views
    from cadio.inspect.register import _Cad, _icp, _steps
    from cadio.inspect.scan import scan_of
    from cadio.records import apply_pose

    mesh = _cylinder_mesh(11, 9, 6)
    surface = part_surface("nut", mesh)
    rises = {True: 0, False: 0}
    for seed in range(6):
        rng = np.random.default_rng(seed)
        truth = _pose(rng.uniform(0, 180), tuple(rng.normal(size=3)), (0, 0, 30))
        capture = CaptureConfig(target_size_m=None, noise=replace(D435, seed=seed),
                                distance_m=0.66, n_views=1, start_deg=rng.uniform(0, 360))
        scan = scan_of(list(render_views([PlacedPart(1, mesh, truth)], capture)))
        points = scan.points[scan.segments[1]]
        model, normals = visible(surface, truth, list(scan.cameras))
        cad = _Cad(model, normals, KDTree(model))
        centre = truth[:3, :3] @ surface.centre + truth[:3, 3]
        for monotone in (True, False):
            poses = [_icp(model, normals, points, truth, centre, 3.0,
                          RegisterConfig(iterations=k, monotone=monotone)) for k in range(10)]
            # each pose's scan in the frame where the CAD stands at ``truth``
            moved = [apply_pose(truth @ np.linalg.inv(pose), points)[None] for pose in poses]
            for one, two in pairwise(moved):
                here = _steps(cad, one, centre, 3.0, 3.0)
                after = _steps(cad, two, centre, 3.0, 3.0, among=here.paired)
                rises[monotone] += int(after.among[0] > here.cost[0] + 1e-9)
    assert rises[True] == 0
    assert rises[False] > 0  # (the check is what keeps it: plain steps do raise it here)


def test_global_search_finds_a_part_without_any_prior_pose() -> None:
    surface = part_surface("l", _l_mesh())
    cameras = [_camera()]
    truth = _pose(130, (1, 2, 0.5), (10, 5, -5))
    scan = _seen(surface, truth, cameras)
    best = global_search(surface, scan, cameras, RegisterConfig(seed=1))[0]
    mm, deg = pose_error(best.pose, truth, symmetry_of(surface.samples))
    assert mm < 0.2 and deg < 0.2, (mm, deg, best.seed)


def test_a_nut_showing_a_band_of_its_flats_is_also_tried_at_either_end_of_its_axis() -> None:
    """A nut under a washer shows a band of its sides: the band fits the nut wherever along
    its axis the rest of it lies, so the search's starts slide it both ways along that axis,
    its shortest, as they do a bolt along its longest (only the depth tells which is right;
    the search slides along the shorter axes where no start agrees with the depth)."""
    from cadio.inspect.register import _slides

    nut = part_surface("nut", _cylinder_mesh(10.0, 8.0))
    a = np.linspace(0, 2 * math.pi, 400, endpoint=False)
    band = np.column_stack([10 * np.cos(a), 10 * np.sin(a), np.tile([-4.0, -3.0, -2.0], 134)[:400]])
    pose = _pose(0, (0, 0, 1), (0, 0, 0))
    shifts = sorted(float(p[2, 3]) for p in _slides(nut, pose, band, axes=(0, 1, 2)))
    assert len(shifts) == 3 and shifts[1] == 0.0
    assert shifts[0] == pytest.approx(-3.0, abs=0.1) and shifts[2] == pytest.approx(3.0, abs=0.1)
    whole = np.column_stack([10 * np.cos(a), 10 * np.sin(a), np.linspace(-4, 4, 400)])
    assert len(_slides(nut, pose, whole, axes=(0, 1, 2))) == 1  # nowhere else to look
    assert len(_slides(nut, pose, band)) == 1  # along its longest axis: all of it seen


def test_a_surface_lying_on_another_segment_s_depth_is_that_segment_s_not_the_hypothesis_s(
        ) -> None:
    cam = _camera()
    label = np.ones((480, 640), dtype=np.int64)
    label[:, 320:] = 2  # the left half of the image is segment 1's, the right half 2's
    scan = Scan(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), (cam,), depths=(
        np.full((480, 640), 300.0),), labels=(label,))

    def at(us: range, depth: float) -> np.ndarray:  # world points at pixels (u, 240)
        k = cam.intrinsics
        local = np.array([[(u - k.cx) * depth / k.fx, 0.0, depth] for u in us])
        rot, t = cam.world_to_camera[:3, :3], cam.world_to_camera[:3, 3]
        return (local - t) @ rot

    own, others = at(range(100, 200), 300.0), at(range(400, 500), 300.0)
    assert consistency(np.vstack([own, others]), scan) == 1.0  # the depth agrees everywhere
    assert consistency(np.vstack([own, others]), scan, segment=1) == pytest.approx(0.5)
    assert consistency(others, scan, segment=2) == 1.0
    # behind the other segment's surface it is hidden there, and counts neither way
    assert consistency(np.vstack([own, at(range(400, 500), 303.0)]), scan, segment=1) == 1.0
    # the camera saw through it: free space, whoever's pixel it is
    assert consistency(at(range(100, 200), 290.0), scan, segment=1) == 0.0


def test_copies_of_a_shape_are_scored_as_the_part_whose_points_they_registered() -> None:
    """Three bolts and a plate: two bolt segments named each other's part are scored as their
    own, each pose read as that part's; a plate's segment registered as a bolt keeps a bolt's
    name (the one no segment of its own was scored as), its pose as that bolt's."""
    from cadio.inspect.register import Fit
    from cadio.inspect.routes import AssemblyModel, Found
    from cadio.inspect.stage import scored_as

    turn = np.eye(4)
    turn[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # bolt 1's frame on bolt 0's
    alike = (np.eye(4), turn, np.eye(4), np.eye(4))
    model = AssemblyModel("toy", (), (), (), ("bolt", "bolt", "bolt", "plate"), alike)

    def found(segment: int, index: int, x: float) -> Found:
        pose = np.eye(4)
        pose[:3, 3] = (x, 0.0, 0.0)
        return Found(segment, index, Fit(model.as_part(index, pose), 1.0, 1.0, 0.1, 100,
                                         np.eye(6), pose[:3, 3], 100))

    segments = [found(10, 1, 5.0), found(11, 0, 7.0), found(12, 2, 9.0)]
    truth = {"instances": {"10": 0, "11": 3, "12": 1}}
    scored = scored_as(model, segments, truth)
    assert {s: i for s, (i, _) in scored.items()} == {10: 0, 12: 1, 11: 2}
    for segment, x in ((10, 5.0), (12, 9.0), (11, 7.0)):
        index, pose = scored[segment]
        first = np.eye(4)
        first[:3, 3] = (x, 0.0, 0.0)
        np.testing.assert_allclose(pose, model.as_part(index, first))


def test_one_shape_however_it_is_turned_and_no_shape_by_small_steps() -> None:
    """A washer laid flat and the same washer tilted in the assembly are one shape (their box
    diagonals in the assembly's axes differ by more than the tolerance); boxes 35, 35.8,
    36.6 and 37.4 mm long, each within a millimetre of the last, are two shapes."""
    from cadio.inspect.routes import shape_keys
    from cadio.records import apply_pose

    washer = _cylinder_mesh(8.0, 3.0)
    tilted = Mesh(apply_pose(_pose(40.0, (1.0, 1.0, 0.0), (50.0, 0.0, 0.0)), washer.vertices),
                  washer.triangles)
    flat, turned = part_surface("flat", washer), part_surface("tilted", tilted)
    assert abs(flat.diameter - turned.diameter) > 1.0
    none = Symmetry((0.0, 0.0, 0.0))
    assert len(set(shape_keys([flat, turned], [none, none]))) == 1
    boxes = [part_surface(f"box{k}", _box_mesh(35.0 + 0.8 * k, 10.0, 10.0)) for k in range(4)]
    keys = shape_keys(boxes, [none] * 4)
    assert keys[0] == keys[1] and keys[2] == keys[3] and keys[0] != keys[2]


def test_candidates_whose_figures_differ_only_in_their_last_bits_tie() -> None:
    """Two fits of one segment whose RMS differ in the last bits (what a process's history can
    change: the order of a sum, the alignment a vector kernel meets) rank alike, and neither
    beats the other, so the first in the search's fixed order stays; a real difference still
    decides."""
    from dataclasses import replace

    from cadio.inspect.register import Fit
    from cadio.inspect.routes import _better

    first = Fit(np.eye(4), 0.9, 0.8, 0.5, 100, np.eye(6), np.zeros(3), 200)
    second = replace(first, rmse_mm=0.5 * (1 + 4e-16) + 1e-13)
    assert first.rmse_mm != second.rmse_mm
    assert first.rank() == second.rank()
    assert not _better(second, first) and not _better(first, second)
    closer = replace(first, rmse_mm=0.499)
    assert closer.rank() > first.rank() and _better(closer, first)
