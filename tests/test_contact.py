"""Tests of cadio.truth.contact and proximity: part geometry, pruning, contact, face overlaps.

Every contact answer is checked against an exact BRepExtrema distance on built solids (boxes,
a cylinder, a sphere, a shaft in a bore) at gaps on both sides of ``contact_mm``; pruning and
overlaps are checked again after a rigid motion of everything.
"""

from __future__ import annotations

import math

import build123d as bd
import numpy as np
import pytest
from OCP.BRep import BRep_Tool
from OCP.BRepExtrema import BRepExtrema_DistShapeShape
from OCP.gp import gp_Trsf
from OCP.TopAbs import TopAbs_EDGE, TopAbs_VERTEX
from OCP.TopExp import TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape
from scipy.spatial.transform import Rotation

from cadio.cad.step import StepSolid
from cadio.records import SolidInfo
from cadio.tolerances import DEFAULT_TOLERANCES as TOL
from cadio.truth.contact import PartGeometry, describe_part, face_overlap
from cadio.truth.proximity import (
    ProxyCache,
    box_pairs,
    close_faces,
    coaxial_bound,
    contact_proxy,
    faces_within,
    in_contact,
)

ROT = Rotation.from_euler("xyz", [37, -61, 113], degrees=True).as_matrix()
SHIFT = np.array([250.0, -1234.5, 77.7])
# Gaps (mm) on both sides of the contact tolerance (0.1 mm), exactly at it included.
GAPS = (0.0, 0.05, 0.1, 0.1005, 0.15, 0.6)


def solid(shape: bd.Shape) -> TopoDS_Shape:
    return TopoDS.Solid_s(shape.solids()[0].wrapped)


def moved(shape: TopoDS_Shape, rot: np.ndarray = ROT, shift: np.ndarray = SHIFT
          ) -> TopoDS_Shape:
    trsf = gp_Trsf()
    trsf.SetValues(*rot[0], shift[0], *rot[1], shift[1], *rot[2], shift[2])
    return shape.Moved(TopLoc_Location(trsf))


def part(shape: TopoDS_Shape, index: int = 0) -> PartGeometry:
    info = SolidInfo(index, f"p{index}", "", np.eye(4), f"asm/p{index}")
    return describe_part(StepSolid(info, TopoDS.Solid_s(shape)), index, str(index), TOL)


def exact_distance(a: TopoDS_Shape, b: TopoDS_Shape) -> float:
    dist = BRepExtrema_DistShapeShape(a, b)
    assert dist.IsDone()
    return float(dist.Value())


def pair_at(kind: str, gap: float) -> tuple[TopoDS_Shape, TopoDS_Shape]:
    """Two solids ``gap`` mm apart: face to face, line, point or shaft-in-bore contact."""
    block = solid(bd.Pos(0, 0, -5) * bd.Box(40, 30, 10))  # top face z = 0
    if kind == "faces":
        return block, solid(bd.Pos(5, 0, 2.5 + gap) * bd.Box(10, 10, 5))
    if kind == "line":
        return block, solid(bd.Pos(0, 0, 5 + gap) * bd.Rot(0, 90, 0) * bd.Cylinder(5, 30))
    if kind == "point":
        return block, solid(bd.Pos(3, -2, 8 + gap) * bd.Sphere(8))
    plate = solid(bd.Box(40, 40, 10) - bd.Cylinder(6, 10))
    return plate, solid(bd.Pos(0, 0, 5) * bd.Cylinder(6 - gap, 30))


# ---------------------------------------------------------------- per-part geometry


def test_planar_faces_carry_outward_normals_centroids_and_reach() -> None:
    geo = part(solid(bd.Pos(10, 20, 30) * bd.Box(40, 30, 10)))
    assert sorted(geo.plane_ids) == list(range(6))
    for fid, n, c, reach in zip(geo.plane_ids, geo.normals, geo.centres, geo.reach,
                                strict=True):
        axis = int(np.argmax(np.abs(n)))
        half = np.array([20.0, 15.0, 5.0])
        np.testing.assert_allclose(c, [10, 20, 30] + n * half, atol=1e-9, err_msg=str(fid))
        others = [k for k in range(3) if k != axis]
        assert reach == pytest.approx(float(np.linalg.norm(half[others])), rel=1e-9)


def test_axis_lines_merge_coaxial_faces_with_their_extent_and_convexity() -> None:
    bolt = bd.Cylinder(5, 30, align=bd.Align.NONE) + bd.Pos(0, 0, 30) * bd.Cylinder(
        8, 5, align=bd.Align.NONE)
    geo = part(solid(bd.Pos(7, 0, 0) * bd.Rot(0, 90, 0) * bolt))
    (line,) = geo.lines
    assert abs(line.direction[0]) == pytest.approx(1.0)
    np.testing.assert_allclose(np.sort(line.ends[:, 0]), [7, 42], atol=1e-9)
    assert sorted((f.radius, f.convex) for f in line.faces) == [(5.0, True), (8.0, True)]
    plate = part(solid(bd.Box(40, 40, 10) - bd.Cylinder(6, 10)))
    (hole,) = plate.lines
    (face,) = hole.faces
    assert (face.radius, face.convex) == (pytest.approx(6.0), False)
    np.testing.assert_allclose(np.sort(face.ends[:, 2]), [-5, 5], atol=1e-9)


def test_cone_faces_carry_their_radius_at_every_station() -> None:
    """A 30 degree conical recess (r=3 at z=6 to r=5.31 at z=10) in a plate: the cone's radii
    at its ends come from its boundary, whatever radius OCCT keeps as the cone's reference."""
    slope = math.tan(math.radians(30))
    plate = bd.Pos(0, 0, 5) * bd.Box(40, 40, 10) - bd.Pos(0, 0, 8) * bd.Cone(3.0, 3 + 4 * slope, 4)
    (line,) = part(solid(bd.Pos(5, -3, 0) * plate)).lines
    (cone,) = [f for f in line.faces if f.kind == "cone"]
    assert not cone.convex
    np.testing.assert_allclose(cone.radii, [3.0, 3 + 4 * slope])  # lowest end first
    np.testing.assert_allclose(cone.ends[:, 2], [6.0, 10.0], atol=1e-9)
    up = np.array([0.0, 0.0, 1.0])
    assert cone.radius_at(np.array([5.0, -3.0, 8.0])) == pytest.approx(3 + 2 * slope, abs=1e-9)
    assert cone.radius_at(np.array([5.0, -3.0, 12.0])) == pytest.approx(3 + 6 * slope, abs=1e-9)
    assert cone.semi_angle_deg(up) == pytest.approx(30.0, abs=1e-9)
    assert cone.semi_angle_deg(-up) == pytest.approx(-30.0, abs=1e-9)


# ---------------------------------------------------------------- pruning and contact


def test_box_pairs_keeps_boxes_within_the_margin() -> None:
    parts = [part(solid(bd.Pos(x, 0, 0) * bd.Box(10, 10, 10)), k)
             for k, x in enumerate((0.0, 10.15, 40.0))]
    assert box_pairs(parts, 0.2) == [(0, 1)]
    assert box_pairs(parts, 0.1) == []
    assert box_pairs(parts[:1], 1e3) == []


def test_box_pairs_never_drops_a_pair_within_the_margin_after_a_rigid_motion() -> None:
    shapes = [solid(bd.Pos(x, y, 0) * bd.Rot(0, 0, a) * bd.Box(10, 4, 4))
              for x, y, a in ((0, 0, 0), (9.5, 3, 30), (3, 9, 75), (30, 0, 10))]
    for shapes_now in (shapes, [moved(s) for s in shapes]):
        parts = [part(s, k) for k, s in enumerate(shapes_now)]
        kept = set(box_pairs(parts, 2 * TOL.contact_mm))
        for i in range(len(parts)):
            for j in range(i + 1, len(parts)):
                if exact_distance(shapes_now[i], shapes_now[j]) <= 2 * TOL.contact_mm:
                    assert (i, j) in kept


@pytest.mark.parametrize("kind", ["faces", "line", "point", "bore"])
@pytest.mark.parametrize("gap", GAPS)
def test_in_contact_agrees_with_the_exact_distance(kind: str, gap: float) -> None:
    a, b = pair_at(kind, gap)
    expected = exact_distance(a, b) <= TOL.contact_mm * (1 + 1e-9)
    assert expected == (gap <= TOL.contact_mm)  # the built geometry is what it says
    pa, pb = part(a, 0), part(b, 1)
    assert in_contact(contact_proxy(a, pa.plane_ids), contact_proxy(b, pb.plane_ids),
                      TOL.contact_mm) == expected
    ma, mb = moved(a), moved(b)
    assert in_contact(contact_proxy(ma), contact_proxy(mb), TOL.contact_mm) == expected


def test_a_solid_held_inside_another_is_in_contact() -> None:
    outer = solid(bd.Box(40, 40, 40))
    inner = solid(bd.Sphere(5))
    assert in_contact(contact_proxy(outer), contact_proxy(inner), TOL.contact_mm)
    assert in_contact(contact_proxy(inner), contact_proxy(outer), TOL.contact_mm)


def test_contact_proxy_bounds_every_face_by_its_samples() -> None:
    shape = solid(bd.Sphere(8) + bd.Pos(0, 0, 10) * bd.Cylinder(3, 20))
    proxy = contact_proxy(shape)
    assert len(proxy.faces) == len(proxy.triangles) == len(proxy.boxes)
    for k, (face, box) in enumerate(zip(proxy.faces, proxy.boxes, strict=True)):
        samples = proxy.samples(k)
        assert samples is not None
        assert np.all(samples >= box[:3] - proxy.slack) and np.all(samples <= box[3:] + proxy.slack)
        vertex = bd.Vertex(*samples[len(samples) // 2]).wrapped
        assert exact_distance(vertex, face) <= proxy.slack


def test_faces_within_measures_only_the_listed_pairs() -> None:
    a, b = pair_at("faces", 0.05)
    pa, pb = part(a), part(b)
    top = next(i for i, n in zip(pa.plane_ids, pa.normals, strict=True) if n[2] > 0.5)
    bottom = next(i for i, n in zip(pb.plane_ids, pb.normals, strict=True) if n[2] < -0.5)
    lid = next(i for i, n in zip(pb.plane_ids, pb.normals, strict=True) if n[2] > 0.5)
    assert faces_within(pa.faces, pb.faces, [(top, bottom)], TOL.contact_mm)
    assert faces_within(pa.faces, pb.faces, [(top, lid), (top, bottom)], TOL.contact_mm)
    assert faces_within(pa.faces, pb.faces, [(top, bottom)], 0.05)  # at the limit is in
    assert not faces_within(pa.faces, pb.faces, [(top, bottom)], 0.04)
    assert not faces_within(pa.faces, pb.faces, [(top, lid)], 5.0)  # 5.05 mm apart
    assert not faces_within(pa.faces, pb.faces, [], TOL.contact_mm)


# ---------------------------------------------------------------- face overlap


def opposed(a: TopoDS_Shape, b: TopoDS_Shape) -> tuple[PartGeometry, int, PartGeometry, int]:
    """The upward face of a with the largest z and the downward face of b with the lowest z."""
    pa, pb = part(a, 0), part(b, 1)
    ka = max((k for k in range(len(pa.plane_ids)) if pa.normals[k, 2] > 0.5),
             key=lambda k: pa.centres[k, 2])
    kb = min((k for k in range(len(pb.plane_ids)) if pb.normals[k, 2] < -0.5),
             key=lambda k: pb.centres[k, 2])
    return pa, ka, pb, kb


def tolerances(face: TopoDS_Face) -> list[float]:
    """The tolerances of a face, its edges and its vertices, mm."""
    out = [BRep_Tool.Tolerance_s(face)]
    for kind, cast in ((TopAbs_EDGE, TopoDS.Edge_s), (TopAbs_VERTEX, TopoDS.Vertex_s)):
        explorer = TopExp_Explorer(face, kind)
        while explorer.More():
            out.append(BRep_Tool.Tolerance_s(cast(explorer.Current())))
            explorer.Next()
    return out


def overlap(pa: PartGeometry, ka: int, pb: PartGeometry, kb: int) -> tuple[float, np.ndarray]:
    return face_overlap(pa.faces[pa.plane_ids[ka]], pb.faces[pb.plane_ids[kb]],
                        pa.normals[ka], pa.centres[ka], pb.normals[kb], pb.centres[kb])


@pytest.mark.parametrize(("dx", "dy", "area", "centre"), [
    (0.0, 0.0, 100.0, (0.0, 0.0)),  # b's whole bottom on a's top
    (20.0, 0.0, 50.0, (17.5, 0.0)),  # half of it over a's edge
    (20.0, 15.0, 25.0, (17.5, 12.5)),  # a quarter, at a's corner
    (25.0, 0.0, 0.0, None),  # beside a, sharing an edge line only
    (25.0, 20.0, 0.0, None),  # sharing a corner point only
])
def test_overlap_area_of_opposed_faces(dx: float, dy: float, area: float,
                                       centre: tuple[float, float] | None) -> None:
    a = solid(bd.Pos(0, 0, -5) * bd.Box(40, 30, 10))
    b = solid(bd.Pos(dx, dy, 2.5) * bd.Box(10, 10, 5))
    got, where = overlap(*opposed(a, b))
    assert got == pytest.approx(area, abs=TOL.min_overlap_mm2)
    if centre is not None:
        np.testing.assert_allclose(where, [*centre, 0.0], atol=1e-6)


def test_overlap_of_a_washer_on_a_drilled_plate_is_the_annulus_outside_the_hole() -> None:
    plate = solid(bd.Pos(0, 0, -5) * bd.Box(40, 40, 10) - bd.Cylinder(5.016, 12))
    washer = solid(bd.Pos(0, 0, 0.8) * (bd.Cylinder(7.94, 1.6) - bd.Cylinder(4.889, 2)))
    got, where = overlap(*opposed(plate, washer))
    assert got == pytest.approx(math.pi * (7.94**2 - 5.016**2), rel=1e-6)
    np.testing.assert_allclose(where, [0, 0, 0], atol=1e-6)


def test_overlap_is_unchanged_by_a_rigid_motion() -> None:
    a = solid(bd.Pos(0, 0, -5) * bd.Box(40, 30, 10))
    b = solid(bd.Pos(20, 15, 2.55) * bd.Box(10, 10, 5))  # on a's corner, 0.05 mm above it
    pa, ka, pb, kb = opposed(a, b)
    area, where = overlap(pa, ka, pb, kb)
    ma, mb = part(moved(a), 0), part(moved(b), 1)
    got, got_where = overlap(ma, ka, mb, kb)  # face ids and order survive the motion
    assert area == pytest.approx(25.0, rel=1e-9)
    assert got == pytest.approx(area, rel=1e-9)
    np.testing.assert_allclose(got_where, ROT @ where + SHIFT, atol=1e-6)


@pytest.mark.parametrize("size", [10.0, 100.0, 1000.0])
def test_faces_touching_exactly_overlap_when_the_given_normal_is_off_by_rounding(
        size: float) -> None:
    """A plane group's normal is an area-weighted mean, off a face's own normal by rounding:
    the Boolean needs its fuzzy value, or over a large face the two share nothing."""
    a = solid(bd.Pos(0, 0, -5) * bd.Box(2 * size, 2 * size, 10))
    b = solid(bd.Pos(0, 0, 2.5) * bd.Box(size, size, 5))
    pa, ka, pb, kb = opposed(a, b)
    tilt = 1e-7 * 100.0 / size  # 1e-5 mm of misfit across the face at every size
    na = np.array([math.sin(tilt), 0.0, math.cos(tilt)])
    fa, fb = pa.faces[pa.plane_ids[ka]], pb.faces[pb.plane_ids[kb]]
    exact, _ = face_overlap(fa, fb, na, pa.centres[ka], pb.normals[kb], pb.centres[kb], 0.0)
    assert exact == 0.0  # what an exact Boolean makes of it
    before = tolerances(fa) + tolerances(fb)
    area, _ = face_overlap(fa, fb, na, pa.centres[ka], pb.normals[kb], pb.centres[kb])
    assert area == pytest.approx(size**2, rel=1e-6)
    assert tolerances(fa) + tolerances(fb) == before  # the faces are left as they were
    again, _ = face_overlap(fa, fb, na, pa.centres[ka], pb.normals[kb], pb.centres[kb], 0.0)
    assert again == 0.0


# ---------------------------------------------------------------- coaxial faces


def coaxial_pair(dz: float, gap: float, arc: float = 360.0) -> tuple[TopoDS_Shape, TopoDS_Shape]:
    """A plate with a bore r=6, and a shaft r=6-gap (an ``arc`` degree sector of it) starting
    dz mm above the plate's top face (z=10)."""
    plate = solid(bd.Pos(0, 0, 5) * bd.Box(40, 40, 10) - bd.Cylinder(6, 30))
    shaft = bd.Pos(0, 0, 10 + dz + 10) * bd.Cylinder(6 - gap, 20, arc_size=arc)
    return plate, solid(shaft)


@pytest.mark.parametrize(("dz", "gap", "arc"), [
    (-15.0, 0.0, 360), (-15.0, 0.3, 360), (-15.0, 2.5, 360), (0.5, 0.0, 360), (3.0, 0.2, 360),
    (-15.0, 0.3, 90), (8.0, 4.0, 200),
])
def test_coaxial_bound_never_exceeds_the_exact_distance(dz: float, gap: float,
                                                        arc: float) -> None:
    for a, b in (coaxial_pair(dz, gap, arc), (moved(coaxial_pair(dz, gap, arc)[0]),
                                              moved(coaxial_pair(dz, gap, arc)[1]))):
        pa, pb = part(a, 0), part(b, 1)
        proxy_a, proxy_b = contact_proxy(a), contact_proxy(b)
        (line,) = pa.lines
        for fa in line.faces:
            for fb in (f for ln in pb.lines for f in ln.faces):
                exact = exact_distance(pa.faces[fa.face_id], pb.faces[fb.face_id])
                bound = coaxial_bound(proxy_a, fa.face_id, proxy_b, fb.face_id, line.mid,
                                      line.direction)
                assert bound <= exact + 1e-9
                assert bound >= exact - 2 * (proxy_a.mesh_slack + proxy_b.mesh_slack) - 1e-9


def test_coaxial_bound_rules_out_a_nested_ring_the_boxes_cannot() -> None:
    """A shaft 2.5 mm inside the bore: the boxes of the two cylinders overlap, the bound does
    not."""
    plate, shaft = coaxial_pair(-15.0, 2.5)
    pa, pb = part(plate, 0), part(shaft, 1)
    (bore,) = pa.lines[0].faces
    (side,) = [f for f in pb.lines[0].faces]
    cache = ProxyCache([pa, pb])
    assert close_faces(cache[0], cache[1], [(bore.face_id, side.face_id)], 2.0) == {}
    assert cache.boxes(0)[bore.face_id][0] < cache.boxes(1)[side.face_id][0]  # nested boxes
    bound = coaxial_bound(cache[0], bore.face_id, cache[1], side.face_id, pa.lines[0].mid,
                          pa.lines[0].direction)
    assert bound > 1.0


def test_close_faces_returns_exact_distances_within_the_limit_only() -> None:
    plate, shaft = coaxial_pair(0.5, 0.0)  # the shaft starts 0.5 mm above the bore
    pa, pb = part(plate, 0), part(shaft, 1)
    cache = ProxyCache([pa, pb])
    (bore,) = pa.lines[0].faces
    pairs = [(bore.face_id, f.face_id) for f in pb.lines[0].faces] + [(bore.face_id, 0)]
    found = close_faces(cache[0], cache[1], pairs, 0.5)  # at the limit is in
    assert list(found.values()) == [pytest.approx(0.5, abs=1e-9)]
    assert close_faces(cache[0], cache[1], pairs, 0.49) == {}
    assert cache[0] is cache[0]  # built once
