"""Fitted-primitive evidence of a pair's mates, on CAD surface samples of real solids."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cadio.cad.tessellate import tessellate
from cadio.evidence.cad_samples import surface_samples
from cadio.evidence.pair_features import (
    N_PAIR_FEATURES,
    PAIR_FEATURES,
    FeatureConfig,
    dominant_direction,
    pair_features,
    pair_features_many,
    part_cloud,
)

F = {name: i for i, name in enumerate(PAIR_FEATURES)}


def _points(shape, seed: int = 0, n: int = 600) -> np.ndarray:  # type: ignore[no-untyped-def]
    return surface_samples(tessellate(shape.wrapped), n, seed)


@pytest.fixture(scope="module")
def solids():  # type: ignore[no-untyped-def]
    import build123d as bd

    plate = bd.Box(60, 40, 6) - bd.Cylinder(5, 6)
    return {
        "plate": plate,
        "pin": bd.Pos(0, 0, 10) * bd.Cylinder(5, 30),  # in the plate's bore: concentric
        "far_pin": bd.Pos(25, 0, 30) * bd.Cylinder(5, 30),  # parallel axis 25 mm away
        "block": bd.Pos(0, 0, 8) * bd.Box(30, 30, 10),  # resting on the plate: coincident
        "lifted": bd.Pos(0, 0, 13) * bd.Box(30, 30, 10),  # 5 mm above it
    }


def _features(solids, a: str, b: str) -> np.ndarray:  # type: ignore[no-untyped-def]
    return pair_features(part_cloud(_points(solids[a], 1)), part_cloud(_points(solids[b], 2)))


def test_a_pin_in_a_bore_is_coaxial_and_near(solids) -> None:  # type: ignore[no-untyped-def]
    near, far = _features(solids, "plate", "pin"), _features(solids, "plate", "far_pin")
    assert near.shape == (N_PAIR_FEATURES,)
    # 600 samples of a 60 mm plate put about 18 on its bore: the pin's axis, the bore's circle
    assert near[F["contact_axis_found"]] == 1 and near[F["contact_axis_flatness"]] < 0.2
    assert near[F["contact_axis_offset_mm"]] < 0.6 and near[F["contact_radius_diff_mm"]] < 1.0
    assert far[F["contact_axis_found"]] == 0 and far[F["gap_mm"]] > 5
    # five times the points put the bore's and the pin's circles within the mate's 1 mm
    dense = pair_features(part_cloud(_points(solids["plate"], 1, 3000)),
                          part_cloud(_points(solids["pin"], 2, 3000)))
    assert dense[F["contact_axis_offset_mm"]] < min(near[F["contact_axis_offset_mm"]], 0.3)
    assert dense[F["contact_radius_diff_mm"]] < near[F["contact_radius_diff_mm"]]


def test_a_block_resting_on_a_plate_has_opposed_touching_faces(solids) -> None:  # type: ignore[no-untyped-def]
    resting, lifted = _features(solids, "plate", "block"), _features(solids, "plate", "lifted")
    assert resting[F["contact_plane_found"]] == 1 and lifted[F["contact_plane_found"]] == 0
    assert resting[F["contact_plane_normal"]] > 0.9 and resting[F["contact_extent_mm"]] > 5
    assert resting[F["gap_mm"]] < 1.0 and lifted[F["gap_mm"]] > 4.0
    assert resting[F["dom_found"]] == 1 and resting[F["dom_angle_deg"]] < 2.0


def test_a_block_resting_on_a_plate_is_a_face_pair_and_geometric_says_coincident(solids) -> None:  # type: ignore[no-untyped-def]
    from models.geometric import geometric_decisions
    from models.relations import RELATIONS

    resting, lifted = _features(solids, "plate", "block"), _features(solids, "plate", "lifted")
    # the block's bottom on the plate's top: planes within a degree, no offset, a large overlap,
    # the plate below and the block above the face pair
    assert resting[F["face_found"]] == 1 and resting[F["face_opposed"]] == 1
    assert resting[F["face_angle_deg"]] < 1.0 and resting[F["face_offset_mm"]] < 0.1
    assert resting[F["face_overlap_mm2"]] > 100
    assert lifted[F["face_found"]] == 0 and lifted[F["face_overlap_mm2"]] == 0
    # the pin in the bore touches the plate along a cylinder: no face pair is opposed there
    pin = _features(solids, "plate", "pin")
    assert pin[F["face_opposed"]] < 1 or pin[F["face_offset_mm"]] > 1.0
    points = np.stack([np.stack([_points(solids["plate"], 1), _points(solids[b], 2)])
                       for b in ("block", "lifted", "pin")]).astype(np.float32)
    features = np.stack([resting, lifted, pin])
    coincident = geometric_decisions(points, np.ones(3), features)[:, RELATIONS.index(
        "coincident")]
    assert coincident.tolist() == [True, False, False]


def test_exact_faces_touching_within_the_contact_tolerance_come_first() -> None:
    """A caster's fork rests on its plate on two narrow faces beside a wider pair 2 mm apart.
    Where the planes are the faces' own, the touching pair is the evidence; fitted planes keep
    the widest opposed pair (their offsets carry the points' noise)."""
    from cadio.evidence.pair_features import FacePair, _face_pair

    wide = FacePair(angle_deg=0.0, offset_mm=2.0, area_mm2=120.6, opposed=1.0)
    touching = FacePair(angle_deg=0.0, offset_mm=0.0, area_mm2=57.9, opposed=1.0)
    flush = FacePair(angle_deg=0.0, offset_mm=0.0, area_mm2=300.0, opposed=0.0)
    assert _face_pair([wide, touching, flush], exact=True)[2] == 0.0
    assert _face_pair([wide, touching, flush], exact=True)[3] == 57.9
    assert _face_pair([wide, touching, flush])[2] == 2.0
    assert _face_pair([flush], exact=True)[4] == 0.0


def test_a_face_pair_knows_parts_side_by_side_from_parts_face_to_face() -> None:
    from cadio.evidence.pair_features import _face_pair, face_pairs

    def face_pairs_best(a, b, reach, cfg):  # type: ignore[no-untyped-def]
        return _face_pair(face_pairs(a, b, reach, cfg))

    # two plates side by side 0.5 mm apart, their tops flush: the tops overlap within reach,
    # but both parts lie below them (no mate); the facing sides are the opposed pair
    grid = np.stack(np.meshgrid(np.linspace(-20, 0, 21), np.linspace(-10, 10, 21)), -1)
    top = np.column_stack([grid.reshape(-1, 2), np.zeros(441)])
    bottom = top - [0, 0, 4.0]
    side = np.column_stack([np.zeros(105), np.tile(np.linspace(-10, 10, 21), 5),
                            np.repeat(np.linspace(-4, 0, 5), 21)])
    a = np.concatenate([top, bottom, side])
    b = a * [-1, 1, 1] + [0.5, 0, 0]
    found, angle, offset, _, opposed = face_pairs_best(part_cloud(a), part_cloud(b), 2.0,
                                                  FeatureConfig())
    assert found == 1 and opposed == 1 and angle < 1.0 and abs(offset - 0.5) < 0.05
    # without their sides only the flush tops and bottoms face each other: not opposed
    a2, b2 = np.concatenate([top, bottom]), np.concatenate([top, bottom]) * [-1, 1, 1] + [0.5, 0, 0]
    found, _, offset, _, opposed = face_pairs_best(part_cloud(a2), part_cloud(b2), 2.0,
                                              FeatureConfig())
    assert found == 1 and opposed == 0 and offset < 0.05


def test_features_are_symmetric_and_cached(solids) -> None:  # type: ignore[no-untyped-def]
    a, b = _points(solids["plate"], 1), _points(solids["pin"], 2)
    pairs = np.stack([np.stack([a, b]), np.stack([b, a])]) / 1000.0  # metres
    calls = []

    def counted(points: np.ndarray, normals: np.ndarray | None):  # type: ignore[no-untyped-def]
        calls.append(len(points))
        return part_cloud(points, normals=normals)

    out = pair_features_many(pairs, [1000.0, 1000.0], [("p", "q"), ("q", "p")], counted)
    assert np.allclose(out[0], out[1]) and len(calls) == 2
    assert np.allclose(out[0], _features(solids, "plate", "pin"), atol=1e-4)



def test_a_pair_of_clouds_met_again_is_measured_once(solids, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The CAD samples of two parts are the same in every view of them: the pair's evidence
    is measured once, in one call and, through a shared memo, in later ones."""
    import cadio.evidence.pair_features as features

    a, b, c = (_points(solids[k], s) / 1000.0 for k, s in (("plate", 1), ("pin", 2),
                                                          ("block", 3)))
    measured = []

    def counted(x, y, *args):  # type: ignore[no-untyped-def]
        measured.append(1)
        return pair_features(x, y, *args)

    plain = pair_features_many([(a, b), (a, c)], [1000.0, 1000.0])
    monkeypatch.setattr(features, "pair_features", counted)
    memo: dict = {}
    views = pair_features_many([(a, b), (a, c), (a, b)], [1000.0] * 3,
                               [("p", "q"), ("p", "r"), ("p", "q")], memo=memo)
    assert len(measured) == 2 and np.array_equal(views[0], views[2])
    assert np.array_equal(views[:2], plain)
    later = pair_features_many([(a, c)], [1000.0], [("p", "r")], memo=memo)
    assert len(measured) == 2 and np.array_equal(later[0], plain[1])
    # without keys every row is measured
    pair_features_many([(a, b), (a, b)], [1000.0, 1000.0])
    assert len(measured) == 4

def test_clouds_of_any_sizes_and_frames_give_the_features_of_the_stacked_pair(solids) -> None:  # type: ignore[no-untyped-def]
    a, b = _points(solids["plate"], 1), _points(solids["pin"], 2)
    stacked = pair_features_many(np.stack([np.stack([a, b])]), [1.0])[0]
    assert np.allclose(pair_features_many([(a, b)], [1.0])[0], stacked)
    # the evidence is rigid-motion invariant: the pair turned and moved reads the same
    turn = np.array([[0.0, -1.0, 0.0], [0.6, 0.0, -0.8], [0.8, 0.0, 0.6]])
    moved = [(a @ turn.T + 40.0, b @ turn.T + 40.0)]
    assert np.allclose(pair_features_many(moved, [1.0])[0], stacked, atol=1e-3)
    # a denser pin (another size than the plate's cloud) is measured as it is: finer spacing
    dense = pair_features_many([(a, _points(solids["pin"], 2, 2400))], [1.0])[0]
    spacing = PAIR_FEATURES.index("spacing_mm")
    assert dense[spacing] <= stacked[spacing]


def test_the_dominant_direction_of_a_plate_is_its_normal(solids) -> None:  # type: ignore[no-untyped-def]
    normal, ratio = dominant_direction(part_cloud(_points(solids["plate"])))
    assert normal is not None and abs(normal[2]) > math.cos(math.radians(2))
    assert ratio > 3  # faces of 4800 mm^2 against 720: 600 samples put few on the thin sides
    # a pin's side is a cylinder, not strips of tangent planes: its ends are its direction
    normal, ratio = dominant_direction(part_cloud(_points(solids["pin"])))
    assert normal is not None and abs(normal[2]) > math.cos(math.radians(2)) and ratio > 1.5
    assert dominant_direction(part_cloud(np.zeros((3, 3))))[0] is None



def test_a_cylinder_is_refitted_to_its_points_not_left_on_their_normals() -> None:
    """Short arcs of a 30 mm bore seen by CAD samples: local PCA tilts the normals of a few
    points, so an axis read from them is degrees off; the refit to the points is not."""
    import build123d as bd

    from cadio.evidence.fits import axis_of, fit_cylinders

    def tilt(u: np.ndarray) -> float:  # from the bore's axis, +Z
        return math.degrees(math.acos(min(1.0, abs(float(u[2])))))

    from_normals, refitted = [], []
    for y in (26, 28):  # the bore cuts an arc of 60 / 40 mm chord out of the block's side
        arc = bd.Box(40, 40, 8) - bd.Pos(0, y, 0) * bd.Cylinder(30, 8)
        for seed in (1, 2, 3):
            cloud = part_cloud(_points(arc, seed, 1500))
            curved = np.flatnonzero(~cloud.planar)
            fits = fit_cylinders(cloud.points[curved], cloud.normals[curved], cloud.spacing)
            bore = max(fits, key=lambda c: len(c.members))
            assert abs(bore.radius - 30.0) < 0.6
            from_normals.append(tilt(axis_of(cloud.normals[curved][bore.members])[0]))
            refitted.append(tilt(bore.axis))
    assert np.mean(refitted) < 1.0 and np.mean(refitted) < 0.5 * np.mean(from_normals)
    assert max(refitted) < 2.0


def test_the_networks_evidence_is_the_encoded_evidence_the_tests_answers_and_the_direction(
        solids) -> None:  # type: ignore[no-untyped-def]
    from cadio.evidence.pair_features import encode_features
    from models.geometric import (
        DIRECTION_GAIN,
        EVIDENCE,
        GEOMETRIC_ANSWERS,
        PAIR_DIRECTION,
        geometric_decisions,
        network_evidence,
        swap_evidence,
    )

    features = np.stack([_features(solids, "plate", b) for b in ("block", "lifted", "pin")])
    points = np.stack([np.stack([_points(solids["plate"], 1), _points(solids[b], 2)])
                       for b in ("block", "lifted", "pin")]).astype(np.float32)
    seen = network_evidence(features, points)
    assert seen.shape == (3, len(EVIDENCE))
    assert np.array_equal(seen[:, :N_PAIR_FEATURES], encode_features(features))
    answers = geometric_decisions(points, np.ones(3), features)[:, 6:]
    end = N_PAIR_FEATURES + len(GEOMETRIC_ANSWERS)
    assert np.array_equal(seen[:, N_PAIR_FEATURES:end], answers.astype(np.float32))
    # the block resting on the plate is coincident by the tests, the lifted one is not
    assert seen[:, end - 1].tolist() == [1.0, 0.0, 0.0]
    # the direction from b's points' mean to a's: the plate lies below what rests on it
    offset = points[:, 0].mean(1) - points[:, 1].mean(1)
    direction = seen[:, end:end + len(PAIR_DIRECTION)]
    assert direction.shape == (3, len(PAIR_DIRECTION))
    unit = offset / np.linalg.norm(offset, axis=1, keepdims=True)
    assert np.allclose(direction, DIRECTION_GAIN * unit, atol=1e-5)
    assert (direction[:, 2] < -0.5 * DIRECTION_GAIN).all()
    # given centres replace the means; the swapped pair reads the direction negated
    centres = np.zeros((3, 2, 3))
    centres[:, 0, 0] = 5.0
    assert np.allclose(network_evidence(features, points, centres)[:, end:end + 3],
                       [[DIRECTION_GAIN, 0, 0]] * 3)
    swapped = swap_evidence(seen)
    assert np.array_equal(swapped[:, end:], -seen[:, end:])
    assert np.array_equal(swapped[:, :end], seen[:, :end])


def test_cone_codes_cross_one_on_the_truths_cone_edge_and_are_odd() -> None:
    """A cone code is near 2 inside the + cone of its axis, -2 inside the - cone, 0 between,
    and crosses 1 on the truth's own edge: 14 and 16 degrees off an axis lie on either side."""
    from cadio.tolerances import DEFAULT_TOLERANCES
    from models.geometric import cone_codes

    cone = DEFAULT_TOLERANCES.direction_cone_deg

    def off_up(deg: float, towards: tuple[float, float]) -> list[float]:
        r = np.radians(deg)  # tilted from +Z towards (x, y)
        return [np.sin(r) * towards[0], np.sin(r) * towards[1], np.cos(r)]

    offsets = np.array([off_up(0.0, (1, 0)), off_up(cone - 1, (1, 0)), off_up(cone + 1, (0, 1)),
                        off_up(cone, (1, 0)), off_up(45.0, (1, 0)), off_up(90.0, (0, 1)),
                        [0.0, 0.0, 0.0]])
    centres = np.zeros((len(offsets), 2, 3))
    centres[:, 0] = offsets + 0.25
    centres[:, 1] = 0.25  # b's centre, a's at b + offset (metres: any unit)
    codes = cone_codes(centres)
    up = codes[:, 2]
    assert up[0] > 1.9 and up[1] > 1.2 and up[2] < 0.8 and abs(up[3] - 1.0) < 1e-3
    assert abs(up[4]) < 0.01 and abs(up[5]) < 1e-6
    assert codes[5, 1] > 1.9  # 90 degrees from up, straight behind: inside the behind cone
    assert np.array_equal(codes[6], np.zeros(3))  # no direction, no cone
    assert np.allclose(cone_codes(centres[:, ::-1]), -codes, atol=1e-6)


def test_geometric_directions_follow_the_given_centres_not_the_points() -> None:
    """Surface samples crowd where a part has much surface (a thin fin), its solid's centroid
    lies elsewhere: the directional tests read the centres where the input knows them."""
    from models.geometric import geometric_decisions
    from models.relations import RELATIONS

    rng = np.random.default_rng(0)
    a = rng.uniform(-1, 1, (300, 3)).astype(np.float32) + np.float32([0, 0, 10])
    b = rng.uniform(-1, 1, (300, 3)).astype(np.float32)
    points = np.stack([a, b])[None]
    above, left = RELATIONS.index("above"), RELATIONS.index("left")
    by_points = geometric_decisions(points, np.ones(1))
    assert by_points[0, above] and not by_points[0, left]
    centres = np.array([[[-10.0, 0.0, 0.0], [0.0, 0.0, 0.0]]])
    by_centres = geometric_decisions(points, np.ones(1), centres=centres)
    assert by_centres[0, left] and not by_centres[0, above]


def test_exact_planes_take_no_spacing_on_a_face_pairs_offset() -> None:
    """On the CAD's own samples a fitted plane is its face's: a bolt head resting on a washer
    1.59 mm above the flange faces the flange, within the 2.7 mm spacing of the samples but not
    in contact. The fitted points' tests take it for coincident; the exact input's do not, and
    faces that touch stay coincident in both."""
    from models.geometric import GeometricTests, geometric_symmetric, tests_for

    raw = np.zeros((2, N_PAIR_FEATURES))
    column = {name: PAIR_FEATURES.index(name) for name in PAIR_FEATURES}
    for row, offset in enumerate((1.5875, 0.0035)):
        raw[row, column["face_found"]] = raw[row, column["face_opposed"]] = 1.0
        raw[row, column["gap_mm"]], raw[row, column["spacing_mm"]] = 0.2, 2.66
        raw[row, column["face_offset_mm"]] = offset
    coincident = -1
    assert geometric_symmetric(raw)[:, coincident].tolist() == [True, True]
    exact = geometric_symmetric(raw, GeometricTests(exact_planes=True))
    assert exact[:, coincident].tolist() == [False, True]
    assert tests_for("truth").exact_planes and not tests_for("partial").exact_planes
    assert not tests_for("partial").exact_planes and not tests_for("completed").exact_planes


def _face(origin, u, v, normal, nu: int, nv: int):  # type: ignore[no-untyped-def]
    """(nu * nv, 6) points on a grid over one planar face with its outward normal."""
    s, t = np.meshgrid(np.linspace(0, 1, nu), np.linspace(0, 1, nv))
    pts = np.asarray(origin) + np.outer(s.ravel(), u) + np.outer(t.ravel(), v)
    return np.column_stack([pts, np.tile(normal, (len(pts), 1))]).astype(np.float64)


def test_a_block_resting_in_a_pocket_faces_its_floor_on_exact_normals() -> None:
    """On the CAD's samples every normal points out of its part, so two faces rest against
    each other when their outward normals meet. A block in a pocket (a pillow block's housing
    on its base) has the pocket's walls beside it, on its own side of the floor, and no other
    point of the base within reach: the parts do not lie on opposite sides there, yet the faces
    are a coincident mate. Flush faces side by side (outward normals alike) stay no mate."""
    from models.geometric import geometric_symmetric, tests_for

    x, y, z = np.eye(3)
    pocket = np.concatenate([
        _face([-10, -10, 0], 20 * x, 20 * y, z, 21, 21),  # floor, facing up
        _face([-10, -10, 0], 20 * y, 10 * z, x, 21, 11),  # the walls, facing into the pocket
        _face([10, -10, 0], 20 * y, 10 * z, -x, 21, 11),
        _face([-14, -10, -12], 20 * y, 22 * z, -x, 21, 23),  # outer sides and the rims
        _face([14, -10, -12], 20 * y, 22 * z, x, 21, 23),
        _face([-14, -10, 10], 4 * x, 20 * y, z, 5, 21),
        _face([10, -10, 10], 4 * x, 20 * y, z, 5, 21),
        _face([-14, -10, -12], 28 * x, 20 * y, -z, 29, 21),  # the base's bottom, out of reach
    ])
    block = np.concatenate([
        _face([-9, -10, 0], 18 * x, 20 * y, -z, 19, 21),  # resting on the floor
        _face([-9, -10, 8], 18 * x, 20 * y, z, 19, 21),
        _face([-9, -10, 0], 20 * y, 8 * z, -x, 21, 9),
        _face([9, -10, 0], 20 * y, 8 * z, x, 21, 9),
    ])

    def cloud(c):  # type: ignore[no-untyped-def]
        return part_cloud(c[:, :3], normals=c[:, 3:])

    f = pair_features(cloud(pocket), cloud(block))
    assert f[F["face_found"]] == 1 and f[F["face_offset_mm"]] < 0.01
    assert f[F["face_opposed"]] == 1
    assert geometric_symmetric(f[None], tests_for("truth"))[0, -1]
    # two slabs side by side, 0.5 mm apart: only their flush tops and bottoms face each other
    slab = block[np.abs(block[:, 5]) > 0.5]
    f = pair_features(cloud(slab), cloud(slab + np.array([18.5, 0, 0, 0, 0, 0])))
    assert f[F["face_found"]] == 1 and f[F["face_offset_mm"]] < 0.01
    assert f[F["face_opposed"]] == 0
    assert not geometric_symmetric(f[None], tests_for("truth"))[0, -1]
