"""Tests of cadio.truth.relations: the paper's logic rules by construction, boundaries, invariance.

Synthetic features (a box, a capped cylinder) stand in for B-rep parts; ``box_features`` and
``cylinder_features`` are also used by tests/test_scenes.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cadio.records import (
    CONVERSE,
    DIRECTIONAL,
    SYMMETRIC,
    AxisGroup,
    Features,
    PlaneGroup,
    Relation,
)
from cadio.tolerances import DEFAULT_TOLERANCES as TOL
from cadio.truth.relations import (
    direction_axes,
    directional_truth,
    relate,
    relation_table,
    view_frame,
)

# ---------------------------------------------------------------- synthetic features


def _plane(normal: int, lo: float, hi: float, area: float, ids: tuple[int, int]) -> PlaneGroup:
    n = np.zeros(3)
    n[normal] = 1.0
    return PlaneGroup(n, 2 * area, ids, (area, area), (lo, hi), (-1, 1))


def box_features(size: tuple[float, float, float] = (40.0, 30.0, 10.0)) -> Features:
    """A box centred on the origin, sides ``size`` (mm): three planar groups of two faces."""
    sx, sy, sz = size
    areas = (sy * sz, sx * sz, sx * sy)
    planes = tuple(
        _plane(k, -size[k] / 2, size[k] / 2, areas[k], (2 * k, 2 * k + 1)) for k in range(3)
    )
    order = sorted(areas, reverse=True)
    half = np.array(size) / 2
    return Features(
        centroid=np.zeros(3), bbox_min=-half, bbox_max=half, volume=sx * sy * sz,
        area=2 * sum(areas), planes=planes, axes=(),
        principal_plane=planes[int(np.argmax(areas))].normal.copy(), principal_axis=None,
        principal_plane_tie=order[1] >= 0.99 * order[0], n_faces=6,
    )


def cylinder_features(radius: float = 8.0, height: float = 30.0) -> Features:
    """A capped cylinder about Z centred on the origin (mm): caps are its principal plane."""
    cap = math.pi * radius**2
    planes = (_plane(2, -height / 2, height / 2, cap, (0, 1)),)
    axis = AxisGroup("cylinder", np.array([0.0, 0.0, 1.0]), np.zeros(3),
                     2 * math.pi * radius * height, (2,), (radius,))
    half = np.array([radius, radius, height / 2])
    return Features(
        centroid=np.zeros(3), bbox_min=-half, bbox_max=half,
        volume=cap * height, area=2 * cap + axis.area, planes=planes, axes=(axis,),
        principal_plane=planes[0].normal.copy(), principal_axis=axis, n_faces=3,
    )


def pose(rot: np.ndarray | None = None, t: tuple | np.ndarray = (0, 0, 0)) -> np.ndarray:
    m = np.eye(4)
    if rot is not None:
        m[:3, :3] = rot
    m[:3, 3] = t
    return m


def rot_about(axis: tuple[float, float, float], deg: float) -> np.ndarray:
    return Rotation.from_rotvec(np.radians(deg) * np.array(axis, dtype=float)).as_matrix()


# ---------------------------------------------------------------- frame


def test_frame_for_cad_view_is_x_right_y_behind_z_up() -> None:
    right, behind, up = view_frame((0, 1, 0))
    assert np.allclose(right, [1, 0, 0]) and np.allclose(behind, [0, 1, 0])
    assert np.allclose(up, [0, 0, 1])
    axes = dict(zip(DIRECTIONAL, direction_axes((0, 1, 0)), strict=True))
    assert np.allclose(axes[Relation.LEFT], [-1, 0, 0])
    assert np.allclose(axes[Relation.FRONT], [0, -1, 0])


def test_frame_uses_the_ground_projection_of_the_view_axis() -> None:
    assert np.allclose(view_frame((0, 2, -5)), view_frame((0, 1, 0)))
    right, _, _ = view_frame((1, 0, 0))  # looking along +X, the right hand is -Y
    assert np.allclose(right, [0, -1, 0])
    with pytest.raises(ValueError):
        view_frame((0, 0, -1))


def test_simple_scene_reads_as_expected() -> None:
    box, cyl = box_features(), cylinder_features()
    a = cyl.transformed(pose(t=(-100, 0, 0)))
    res = relate(a, box)
    assert res.holding() == (Relation.LEFT, Relation.PARALLEL)
    assert relation_table(relate(box, a)) == {
        r.value: r in (Relation.RIGHT, Relation.PARALLEL) for r in Relation}
    assert res.tolerances == TOL


# ---------------------------------------------------------------- the logic rules


def _random_rotation(rng: np.random.Generator) -> Rotation:
    """Mostly one of the 24 cube rotations, slightly perturbed (so planes and axes line up)."""
    if rng.random() < 0.25:
        return Rotation.random(random_state=int(rng.integers(2**31)))
    tilt = math.radians(float(rng.choice([0.0, 0.0, 0.3, 1.0, 3.0])))
    wobble = Rotation.from_rotvec(rng.normal(size=3) / math.sqrt(3) * tilt)
    return Rotation.create_group("O")[int(rng.integers(24))] * wobble


def _principal(f: Features) -> PlaneGroup:
    n = f.principal_plane
    assert n is not None
    return max(f.planes, key=lambda g: abs(float(np.dot(g.normal, n))))


def _snap_planes(a: Features, b: Features, t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Shift t along a's principal normal so a face of b lands on (or near) a face of a."""
    ga, gb = _principal(a), _principal(b)
    n = ga.normal
    sign = 1.0 if np.dot(n, gb.normal) >= 0 else -1.0
    oa = ga.offsets[int(rng.integers(len(ga.offsets)))]
    ob = sign * gb.offsets[int(rng.integers(len(gb.offsets)))]
    eps = float(rng.choice([0.0, 0.05, 0.1, 0.5]))
    return t + n * (oa + eps - ob - float(np.dot(t, n)))


def _snap_axes(a: Features, b: Features, t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Shift t across a's principal axis so b's axis line meets it (or nearly)."""
    assert a.principal_axis is not None and b.principal_axis is not None
    d = a.principal_axis.direction
    gap = b.principal_axis.point + t - a.principal_axis.point
    side = np.cross(d, rng.normal(size=3))
    side *= float(rng.choice([0.0, 0.05, 0.1, 0.5])) / np.linalg.norm(side)
    return t - (gap - np.dot(gap, d) * d) + side


def _random_pair(rng: np.random.Generator) -> tuple[Features, Features]:
    """Two random parts, poses biased towards aligned, coplanar and coaxial configurations."""
    def part() -> Features:
        if rng.random() < 0.5:
            return box_features(tuple(rng.uniform(5, 60, 3)))
        return cylinder_features(rng.uniform(2, 20), rng.uniform(5, 80))

    ra = _random_rotation(rng)
    rb = ra if rng.random() < 0.4 else _random_rotation(rng)
    a = part().transformed(pose(ra.as_matrix()))
    b = part().transformed(pose(rb.as_matrix()))
    axis = direction_axes()[int(rng.integers(6))]
    t = rng.uniform(20, 200) * (axis + rng.normal(size=3) * rng.choice([0.0, 0.1, 0.3, 1.0]))
    aligned = _line_angle(a.principal_plane, b.principal_plane) < 2.0
    if aligned and rng.random() < 0.5:
        t = _snap_planes(a, b, t, rng)
    elif a.principal_axis is not None and b.principal_axis is not None and rng.random() < 0.6:
        t = _snap_axes(a, b, t, rng)
    return a, b.transformed(pose(t=t))


def _line_angle(u: np.ndarray | None, v: np.ndarray | None) -> float:
    assert u is not None and v is not None
    return math.degrees(math.acos(min(1.0, abs(float(np.dot(u, v))))))


def test_logic_rules_hold_over_random_pairs() -> None:
    rng = np.random.default_rng(20240611)
    counts = dict.fromkeys(Relation, 0)
    for _ in range(3000):
        a, b = _random_pair(rng)
        ab, ba = relate(a, b), relate(b, a)
        for r in DIRECTIONAL:
            assert ab[r] == ba[CONVERSE[r]]  # rule (4)
            assert not (ab[r] and ba[r])  # rule (5)
        for r in SYMMETRIC:
            assert ab[r] == ba[r]
        assert not (ab[Relation.PARALLEL] and ab[Relation.PERPENDICULAR])
        assert not (ab[Relation.PARALLEL] and ab[Relation.COINCIDENT])
        assert ab.plane_gap_mm == ba.plane_gap_mm and ab.axis_distance_mm == ba.axis_distance_mm
        if ab.coplanar_faces is not None and ba.coplanar_faces is not None:
            assert ab.coplanar_faces == ba.coplanar_faces[::-1]
        for r, t in zip(Relation, ab.truth, strict=True):
            counts[r] += t
    assert min(counts.values()) >= 30, counts  # every relation was exercised


def test_rotating_parts_and_view_axis_about_z_changes_nothing() -> None:
    rng = np.random.default_rng(7)
    for _ in range(500):
        a, b = _random_pair(rng)
        view = np.array([*rng.normal(size=2), rng.normal()])
        rz = rot_about((0, 0, 1), rng.uniform(0, 360))
        motion = pose(rz, rng.uniform(-500, 500, 3))
        before = relate(a, b, view)
        after = relate(a.transformed(motion), b.transformed(motion), rz @ view)
        assert before.truth == after.truth
        assert np.allclose(before.direction_deg, after.direction_deg, atol=1e-6)


# ---------------------------------------------------------------- boundaries

JUST = 1e-6  # beyond a tolerance by this much (degrees or mm) counts as outside


@pytest.mark.parametrize("view", [(0, 1, 0), (1, 1, 0), (-0.3, -2, 0.4)])
@pytest.mark.parametrize("relation", DIRECTIONAL)
def test_direction_cone_boundary_is_inclusive(relation: Relation, view: tuple) -> None:
    axes = dict(zip(DIRECTIONAL, direction_axes(view), strict=True))
    u = axes[relation]
    side = np.cross(u, [0.3, 0.5, 0.8])
    side /= np.linalg.norm(side)
    box = box_features()
    for extra, expected in [(0.0, True), (JUST, False), (-JUST, True)]:
        theta = math.radians(TOL.direction_cone_deg + extra)
        t = 137.0 * (math.cos(theta) * u + math.sin(theta) * side)
        res = relate(box.transformed(pose(t=t)), box, view)
        assert res[relation] is expected, (extra, res.direction_deg)
        others = [r for r in DIRECTIONAL if r != relation and res[r]]
        assert not others


def test_directional_batch_matches_relate_and_flags_zero_offset() -> None:
    truth, angles = directional_truth(np.array([[0.0, 0, 0], [-10, 0, 0]]))
    assert not truth[0].any() and np.isnan(angles[0]).all()
    assert truth[1].tolist() == [True, False, False, False, False, False]
    assert relate(box_features(), box_features()).direction_undefined


@pytest.mark.parametrize("extra,expected", [(0.0, True), (-0.5, True), (JUST, False)])
def test_parallel_and_perpendicular_boundaries(extra: float, expected: bool) -> None:
    a = box_features()
    far = (0, 0, 50)
    tilted = a.transformed(pose(rot_about((1, 0, 0), TOL.parallel_deg + extra), far))
    assert relate(tilted, a)[Relation.PARALLEL] is expected
    square = a.transformed(pose(rot_about((1, 0, 0), 90 - TOL.parallel_deg - extra), far))
    assert relate(square, a)[Relation.PERPENDICULAR] is expected
    over = a.transformed(pose(rot_about((1, 0, 0), 90 + TOL.parallel_deg + extra), far))
    assert relate(over, a)[Relation.PERPENDICULAR] is expected


@pytest.mark.parametrize("extra,expected", [(0.0, True), (-0.05, True), (JUST, False)])
def test_coincident_boundary_and_parallel_exclusion(extra: float, expected: bool) -> None:
    a = box_features()  # top face at z = 5, b's bottom face lands at 5 + gap
    b = a.transformed(pose(t=(3.0, 1.0, 10.0 + TOL.coplanar_mm + extra)))
    res = relate(b, a)
    assert res[Relation.COINCIDENT] is expected
    assert res[Relation.PARALLEL] is (not expected)
    assert res.coplanar_opposed is True  # b's bottom faces down, a's top faces up
    assert res.plane_gap_mm == pytest.approx(TOL.coplanar_mm + extra, abs=1e-9)


@pytest.mark.parametrize("what", ["angle", "distance"])
@pytest.mark.parametrize("extra,expected", [(0.0, True), (JUST, False)])
def test_concentric_boundaries(what: str, extra: float, expected: bool) -> None:
    a = cylinder_features()
    if what == "angle":  # tilt about a point on the axis midway between the parts
        tilt = pose(rot_about((0, 1, 0), TOL.coaxial_deg + extra))
        motion = pose(t=(0, 0, 30)) @ tilt @ pose(t=(0, 0, 30))
    else:
        motion = pose(t=(TOL.coaxial_mm + extra, 0, 60))
    res = relate(a.transformed(motion), a)
    assert res[Relation.CONCENTRIC] is expected
    assert res[Relation.ABOVE] and relate(a, a.transformed(motion))[Relation.BELOW]


# ---------------------------------------------------------------- undefined and ties


def test_missing_features_make_relations_false_and_flagged() -> None:
    box = box_features()
    bare = Features(np.zeros(3), -np.ones(3), np.ones(3), 8.0, 24.0, (), (), None, None)
    res = relate(bare.transformed(pose(t=(0, 0, 30))), box)
    assert res.plane_undefined and res.axis_undefined
    assert res.holding() == (Relation.ABOVE,)
    assert relate(box, box.transformed(pose(t=(0, 0, 30)))).axis_undefined


def test_tie_flag_is_reported() -> None:
    cube = box_features((20.0, 20.0, 20.0))
    assert cube.principal_plane_tie
    assert relate(cube, box_features()).plane_tie
    assert not relate(box_features(), box_features()).plane_tie


def test_cone_of_90_degrees_is_refused() -> None:
    from dataclasses import replace

    with pytest.raises(ValueError):
        relate(box_features(), box_features(), tol=replace(TOL, direction_cone_deg=90.0))
