"""Tests of cadio.truth.relations: the paper's logic rules by construction, boundaries, invariance.

Synthetic features (a box, a capped cylinder) stand in for B-rep parts; the face mates are
handed in as ``PairContact`` (measured on exact faces in tests/test_labels.py) or estimated from
the features.
"""

from __future__ import annotations

import json
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
    dominant_choice,
)
from cadio.tolerances import DEFAULT_TOLERANCES as TOL
from cadio.truth.relations import (
    DEFAULT_MARGINS,
    PairContact,
    contacts_of_mates,
    direction_axes,
    directional_truth,
    estimate_contact,
    loose_tolerances,
    relate,
    relation_table,
    tight_tolerances,
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
    dominant, runner_up = dominant_choice(planes, TOL.dominant_group_deg,
                                          TOL.dominant_area_ratio)
    return Features(
        centroid=np.zeros(3), bbox_min=-half, bbox_max=half, volume=sx * sy * sz,
        area=2 * sum(areas), planes=planes, axes=(),
        principal_plane=planes[int(np.argmax(areas))].normal.copy(), principal_axis=None,
        principal_plane_tie=order[1] >= 0.99 * order[0], n_faces=6,
        dominant_plane=dominant, dominant_runner_up=runner_up,
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
        dominant_plane=planes[0].normal.copy(),
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


def _random_pair(rng: np.random.Generator) -> tuple[Features, Features]:
    """Two random parts, poses biased towards aligned configurations."""
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
    return a, b.transformed(pose(t=t))


def _random_contact(rng: np.random.Generator) -> PairContact:
    flags = rng.random(4) < 0.3
    return PairContact(*map(bool, flags), float(rng.uniform(0, 0.2)), float(rng.uniform(0, 1.2)))


def test_logic_rules_hold_over_random_pairs() -> None:
    rng = np.random.default_rng(20240611)
    counts = dict.fromkeys(Relation, 0)
    for _ in range(3000):
        a, b = _random_pair(rng)
        contact = _random_contact(rng) if rng.random() < 0.7 else None
        ab, ba = relate(a, b, contact=contact), relate(b, a, contact=contact)
        for r in DIRECTIONAL:
            assert ab[r] == ba[CONVERSE[r]]  # rule (4)
            assert not (ab[r] and ba[r])  # rule (5)
            assert ab.near[list(Relation).index(r)] == ba.near[list(Relation).index(CONVERSE[r])]
        for r in SYMMETRIC:
            assert ab[r] == ba[r]
            assert ab.near[list(Relation).index(r)] == ba.near[list(Relation).index(r)]
        assert not (ab[Relation.PARALLEL] and ab[Relation.PERPENDICULAR])
        assert not (ab[Relation.PARALLEL] and ab[Relation.COINCIDENT])
        assert ab.contact == ba.contact and ab.plane_angle_deg == ba.plane_angle_deg
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
        contact = _random_contact(rng)  # measured on faces: the estimate reads axis-aligned boxes
        before = relate(a, b, view, contact=contact)
        after = relate(a.transformed(motion), b.transformed(motion), rz @ view, contact=contact)
        assert before.truth == after.truth and before.near == after.near
        assert np.allclose(before.direction_deg, after.direction_deg, atol=1e-6)


# ---------------------------------------------------------------- the face mates decide


def test_coincident_and_concentric_are_the_face_mates_answer() -> None:
    """Whatever the features suggest, the measured face mates decide (scenes and assemblies
    alike): parts far apart with a contact say so; parts touching without one do not."""
    box = box_features()
    stacked = box.transformed(pose(t=(3.0, 1.0, 10.0)))  # its bottom on box's top
    assert relate(stacked, box)[Relation.COINCIDENT]  # the estimate: opposed planes touching
    measured = relate(stacked, box, contact=PairContact())
    assert not measured[Relation.COINCIDENT] and measured[Relation.PARALLEL]
    both = relate(stacked, box, contact=PairContact(coincident=True, concentric=True))
    assert both[Relation.COINCIDENT] and both[Relation.CONCENTRIC]
    assert not both[Relation.PARALLEL]  # parallel excludes coincident
    assert both.contact.measured and not relate(stacked, box).contact.measured


def test_parallel_needs_only_dominant_directions() -> None:
    """Two plates side by side on one plane are parallel, not coincident: their faces do not
    face each other (the principal-plane version called them coincident)."""
    plate = box_features((40.0, 30.0, 4.0))
    beside = plate.transformed(pose(t=(60.0, 0.0, 0.0)))
    res = relate(beside, plate)
    assert res[Relation.PARALLEL] and not res[Relation.COINCIDENT]
    assert res.holding() == (Relation.RIGHT, Relation.PARALLEL)


def test_the_estimate_reads_opposed_touching_planes_and_coaxial_axes() -> None:
    box, cyl = box_features(), cylinder_features(8.0, 30.0)
    for lift, expected in [(0.0, True), (TOL.coplanar_mm, True), (TOL.coplanar_mm + 1e-6, False)]:
        up = box.transformed(pose(t=(3.0, 1.0, 10.0 + lift)))
        found = estimate_contact(up, box)
        assert found.coincident is expected and not found.measured
        assert found.coincident_gap_mm == pytest.approx(lift, abs=1e-9)
    for gap, expected in [(0.0, True), (TOL.concentric_gap_mm, True), (1.5, False)]:
        on_top = cyl.transformed(pose(t=(0.0, 0.0, 30.0 + gap)))
        assert estimate_contact(on_top, cyl).concentric is expected
    aside = cyl.transformed(pose(t=(TOL.coaxial_mm * 2, 0.0, 30.0)))
    assert not estimate_contact(aside, cyl).concentric


def test_contact_round_trips_and_reads_from_a_mates_table() -> None:
    c = PairContact(True, False, False, True, 0.01, math.nan)
    back = PairContact.from_dict(json.loads(json.dumps(c.to_dict())))
    assert back.to_dict() == c.to_dict() and math.isnan(back.concentric_gap_mm)
    assert c.to_dict()["concentric_gap_mm"] is None
    rows = [{"part_a": "p", "part_b": "q", "level": "part", "relation": "coincident"},
            {"part_a": "p", "part_b": "q", "level": "face", "relation": "concentric"},
            {"part_a": "q", "part_b": "r", "level": "part", "relation": "left"}]
    found = contacts_of_mates(rows, [["q", "r", "concentric"]])
    assert found[("p", "q")] == found[("q", "p")]
    assert found[("p", "q")].coincident and not found[("p", "q")].concentric
    assert found[("q", "r")].concentric_near and not found[("q", "r")].concentric
    assert ("p", "r") not in found


def test_loose_and_tight_tolerances_bracket_the_nominal_ones() -> None:
    loose, tight = loose_tolerances(TOL), tight_tolerances(TOL)
    for name in ("mate_angle_deg", "coaxial_deg", "contact_mm", "coaxial_mm",
                 "concentric_gap_mm"):
        assert getattr(tight, name) < getattr(TOL, name) < getattr(loose, name), name
    assert tight.contact_mm == DEFAULT_MARGINS.exact_mm and loose.contact_mm == 0.2


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
    k = list(Relation).index(relation)
    for extra, expected in [(0.0, True), (JUST, False), (-JUST, True)]:
        theta = math.radians(TOL.direction_cone_deg + extra)
        t = 137.0 * (math.cos(theta) * u + math.sin(theta) * side)
        res = relate(box.transformed(pose(t=t)), box, view)
        assert res[relation] is expected, (extra, res.direction_deg)
        assert res.near[k] and res.near_boundary()
        others = [r for r in DIRECTIONAL if r != relation and res[r]]
        assert not others
    clear = relate(box.transformed(pose(t=137.0 * u)), box, view)
    assert not clear.near[k]


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
    res = relate(tilted, a)
    assert res[Relation.PARALLEL] is expected
    assert res.near[list(Relation).index(Relation.PARALLEL)] is (extra != -0.5)
    square = a.transformed(pose(rot_about((1, 0, 0), 90 - TOL.parallel_deg - extra), far))
    assert relate(square, a)[Relation.PERPENDICULAR] is expected
    over = a.transformed(pose(rot_about((1, 0, 0), 90 + TOL.parallel_deg + extra), far))
    assert relate(over, a)[Relation.PERPENDICULAR] is expected


# ---------------------------------------------------------------- the dominant plane direction


def _groups(*normals_areas: tuple[tuple[float, float, float], float]) -> tuple[PlaneGroup, ...]:
    out = []
    for k, (n, area) in enumerate(normals_areas):
        v = np.array(n, dtype=float) / np.linalg.norm(n)
        out.append(PlaneGroup(v, area, (k,), (area,), (0.0,), (1,)))
    return tuple(out)


def test_dominant_direction_needs_one_and_a_half_times_the_runner_up() -> None:
    at = _groups(((0, 0, 1), 150.0), ((1, 0, 0), 100.0))
    direction, runner_up = dominant_choice(at, 1.0, 1.5)
    assert direction is not None and np.allclose(direction, [0, 0, 1])
    assert runner_up == pytest.approx(1 / 1.5)
    assert dominant_choice(_groups(((0, 0, 1), 149.9), ((1, 0, 0), 100.0)), 1.0, 1.5)[0] is None
    assert dominant_choice((), 1.0, 1.5) == (None, 0.0)
    single = dominant_choice(_groups(((0, 1, 0), 5.0),), 1.0, 1.5)
    assert single[1] == 0.0 and np.allclose(single[0], [0, 1, 0])


def test_dominant_direction_groups_normals_within_a_degree_sign_ignored() -> None:
    tilt = math.tan(math.radians(0.9))
    groups = _groups(((0, 0, 1), 80.0), ((1, 0, 0), 100.0), ((0, tilt, -1), 80.0))
    direction, runner_up = dominant_choice(groups, 1.0, 1.5)
    assert direction is not None and abs(direction[2]) > 0.9999
    assert runner_up == pytest.approx(100.0 / 160.0)
    apart = _groups(((0, 0, 1), 80.0), ((1, 0, 0), 100.0),
                    ((0, math.tan(math.radians(1.1)), -1), 80.0))
    assert dominant_choice(apart, 1.0, 1.5)[0] is None  # 100 vs 80: no direction dominates


def test_a_part_without_a_dominant_direction_is_never_parallel_and_near_the_boundary() -> None:
    cube = box_features((20.0, 20.0, 20.0))
    assert cube.dominant_plane is None
    res = relate(cube.transformed(pose(t=(0, 0, 50))), box_features())
    assert res.plane_undefined and not res[Relation.PARALLEL] and not res[Relation.PERPENDICULAR]
    k = [list(Relation).index(r) for r in (Relation.PARALLEL, Relation.PERPENDICULAR)]
    assert all(res.near[i] for i in k)
    assert res.holding() == (Relation.ABOVE,)


def test_a_close_dominance_is_near_the_boundary() -> None:
    close = box_features((31.0, 20.0, 30.0))  # 31 x 30 against 30 x 20: runner-up at 0.645
    assert close.dominant_plane is not None
    res = relate(close.transformed(pose(t=(0, 0, 80))), box_features())
    assert res.near[list(Relation).index(Relation.PARALLEL)]
    clear = relate(box_features().transformed(pose(t=(0, 0, 80))), box_features())
    assert not clear.near_boundary()


def test_missing_features_make_relations_false_and_flagged() -> None:
    box = box_features()
    bare = Features(np.zeros(3), -np.ones(3), np.ones(3), 8.0, 24.0, (), (), None, None)
    res = relate(bare.transformed(pose(t=(0, 0, 30))), box)
    assert res.plane_undefined
    assert res.holding() == (Relation.ABOVE,)


def test_features_carry_the_dominant_direction_through_motion_and_json() -> None:
    box = box_features()
    rot = rot_about((1, 2, 3), 37.0)
    moved = box.transformed(pose(rot, (1, 2, 3)))
    assert moved.dominant_plane is not None and box.dominant_plane is not None
    assert abs(float(moved.dominant_plane @ (rot @ box.dominant_plane))) == pytest.approx(1.0)
    back = Features.from_dict(moved.to_dict())
    assert np.array_equal(back.dominant_plane, moved.dominant_plane)
    assert back.dominant_runner_up == moved.dominant_runner_up


def test_cone_of_90_degrees_is_refused() -> None:
    from dataclasses import replace

    with pytest.raises(ValueError):
        relate(box_features(), box_features(), tol=replace(TOL, direction_cone_deg=90.0))
