"""Tests of cadio.cad.features: plane groups, axes, principal choices, freeform recognition."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import build123d as bd
import numpy as np
import pytest
from OCP.Bnd import Bnd_Box
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Surface
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert, BRepBuilderAPI_Transform
from OCP.BRepTools import BRepTools
from OCP.GeomAbs import GeomAbs_BSplineSurface
from OCP.GeomConvert import GeomConvert_SurfToAnaSurf
from OCP.gp import gp_Ax1, gp_Dir, gp_Pnt, gp_Trsf, gp_Vec
from OCP.Standard import Standard_NullObject
from OCP.TopoDS import TopoDS_Face, TopoDS_Shape

from cadio.cad import features as features_module
from cadio.cad.faces import CONE, indexed_faces, recognise_faces
from cadio.cad.features import extract_features, tight_bbox
from cadio.cad.solid_props import part_integrals
from cadio.cad.tessellate import MASS_PROPS_REL_EPS, brep_mass
from cadio.records import Features, FloatArray
from cadio.tolerances import DEFAULT_TOLERANCES
from cadio.workspace import read_features, write_features

AS1 = "assemblies/occt_as1-oc-214-mat.stp"
COS_1_DEG = np.cos(np.radians(1.0))


def moved(shape: TopoDS_Shape, angle: float, axis: tuple[float, float, float],
          shift: tuple[float, float, float]) -> tuple[TopoDS_Shape, np.ndarray]:
    """The shape after a rotation about ``axis`` through the origin then a translation."""
    trsf = gp_Trsf()
    trsf.SetRotation(gp_Ax1(gp_Pnt(0, 0, 0), gp_Dir(*axis)), angle)
    trsf.SetTranslationPart(gp_Vec(*shift))
    pose = np.eye(4)
    for r in range(3):
        for c in range(4):
            pose[r, c] = trsf.Value(r + 1, c + 1)
    return BRepBuilderAPI_Transform(shape, trsf, True).Shape(), pose


def assert_same_features(got: Features, want: Features, tol: float = 1e-6,
                         rel: float = 1e-6) -> None:
    """Equal features (bbox excepted: a rotated box is not the box of the rotated part).

    ``tol`` bounds direction differences; ``rel`` the relative error of mass properties, which
    OCCT integrates adaptively to about 1e-6.
    """
    assert got.volume == pytest.approx(want.volume, rel=rel)
    assert got.area == pytest.approx(want.area, rel=rel)
    np.testing.assert_allclose(got.centroid, want.centroid, atol=1e-4)
    assert (got.n_faces, got.n_freeform_recognised) == (want.n_faces, want.n_freeform_recognised)
    assert [g.face_ids for g in got.planes] == [g.face_ids for g in want.planes]
    for g, w in zip(got.planes, want.planes, strict=True):
        np.testing.assert_allclose(g.normal, w.normal, atol=tol)
        np.testing.assert_allclose(g.offsets, w.offsets, atol=1e-4)
        assert g.outward == w.outward
    assert [a.face_ids for a in got.axes] == [a.face_ids for a in want.axes]
    for a, w in zip(got.axes, want.axes, strict=True):
        assert a.kind == w.kind
        np.testing.assert_allclose(a.direction, w.direction, atol=tol)
        np.testing.assert_allclose(a.point, w.point, atol=1e-4)
        np.testing.assert_allclose(a.radii, w.radii, rtol=1e-6)
    assert (got.principal_plane is None) == (want.principal_plane is None)
    if got.principal_plane is not None:
        np.testing.assert_allclose(got.principal_plane, want.principal_plane, atol=tol)
    assert (got.principal_axis is None) == (want.principal_axis is None)
    if got.principal_axis is not None and want.principal_axis is not None:
        assert got.principal_axis.face_ids == want.principal_axis.face_ids
    assert got.principal_plane_tie == want.principal_plane_tie
    assert got.principal_axis_tie == want.principal_axis_tie
    assert (got.dominant_plane is None) == (want.dominant_plane is None)
    if got.dominant_plane is not None:
        np.testing.assert_allclose(got.dominant_plane, want.dominant_plane, atol=tol)
    assert got.dominant_runner_up == pytest.approx(want.dominant_runner_up, rel=1e-5)


def occt_optimal_box(shape: TopoDS_Shape) -> tuple[float, ...]:
    """OpenCascade's own optimal box of the whole shape."""
    box = Bnd_Box()
    BRepBndLib.AddOptimal_s(shape, box, False, False)
    return tuple(box.Get())


def assert_bbox_is_occts(shape: TopoDS_Shape) -> None:
    """Within the skip margin (1e-6 mm) of OpenCascade's, where its optimisation is right."""
    lo, hi = tight_bbox(shape)
    assert np.allclose([*lo, *hi], occt_optimal_box(shape), rtol=0, atol=1e-6)


def face_samples(face: TopoDS_Face, n: int = 301) -> FloatArray:
    """Points of a face that is its whole parameter box, on an n x n grid of it."""
    surface = BRep_Tool.Surface_s(face)
    u0, u1, v0, v1 = BRepTools.UVBounds_s(face)
    return np.array([surface.Value(float(u), float(v)).Coord()
                     for u in np.linspace(u0, u1, n) for v in np.linspace(v0, v1, n)])


def exact_round_faces(shape: TopoDS_Shape) -> list[TopoDS_Face]:
    """The torus and sphere faces ``tight_bbox`` boxes in closed form."""
    return [face for face in indexed_faces(shape)
            if (hull := features_module._hull_box(face)) is not None and hull[2]]


def axis_check(features: Features, dimension: str) -> tuple[float, float]:
    """(|cos| between the principal axis and the longest/thinnest bbox axis, its centroid gap)."""
    axis = features.principal_axis
    assert axis is not None
    extent = features.bbox_max - features.bbox_min
    index = int(np.argmax(extent) if dimension == "longest" else np.argmin(extent))
    offset = features.centroid - axis.point
    gap = float(np.linalg.norm(offset - np.dot(offset, axis.direction) * axis.direction))
    return abs(float(axis.direction[index])), gap


# ---------------------------------------------------------------- synthetic shapes


def test_box_planes_offsets_and_outward_signs_anywhere() -> None:
    box = bd.Pos(100, 50, -20) * bd.Box(10, 20, 30)
    f = extract_features(box.wrapped)
    assert f.n_faces == 6 and len(f.planes) == 3 and f.axes == () and f.principal_axis is None
    np.testing.assert_allclose(f.centroid, [100, 50, -20], atol=1e-9)
    np.testing.assert_allclose(f.bbox_min, [95, 40, -35], atol=1e-7)
    np.testing.assert_allclose(f.bbox_max, [105, 60, -5], atol=1e-7)
    assert f.area == pytest.approx(2 * (200 + 300 + 600))
    by_normal = {tuple(np.round(g.normal).astype(int)): g for g in f.planes}
    z = by_normal[(0, 0, 1)]
    assert sorted(zip(z.offsets, z.outward, strict=True)) == [
        pytest.approx((-35, -1)), pytest.approx((-5, 1))]
    np.testing.assert_allclose(f.principal_plane, [1, 0, 0])  # the 20 x 30 faces
    assert not f.principal_plane_tie


def test_freeform_cylinder_and_planes_are_recognised() -> None:
    shape = (bd.Pos(3, -4, 5) * bd.Rot(30, 40, 0) * bd.Cylinder(4, 25)).wrapped
    nurbs = BRepBuilderAPI_NurbsConvert(shape, True).Shape()
    kinds = {BRepAdaptor_Surface(f).GetType() for f in indexed_faces(nurbs)}
    assert kinds == {GeomAbs_BSplineSurface}
    exact, fitted = extract_features(shape), extract_features(nurbs)
    assert exact.n_freeform_recognised == 0
    assert fitted.n_freeform_recognised == fitted.n_faces == 3
    assert_same_features(fitted, replace(exact, n_freeform_recognised=3), rel=1e-5)
    assert fitted.principal_axis is not None
    assert fitted.principal_axis.radii == pytest.approx((4.0,))


def without_cone_radii(f: Features) -> Features:
    """The features with cone radii dropped: a cone's reference radius is taken at wherever its
    surface happens to be located, so it differs between two exact descriptions of one cone."""
    axes = tuple(replace(a, radii=()) if a.kind == CONE else a for a in f.axes)
    principal = None if f.principal_axis is None else axes[f.principal_axis_index()]
    return replace(f, axes=axes, principal_axis=principal)


def test_bspline_surfaces_the_converter_rejects_are_fitted(trimmed_bspline) -> None:
    """A cylinder with a conical end, every surface stored as the KCL pipe stores its bevels."""
    shape = (bd.Pos(3, -4, 5) * bd.Rot(30, 40, 0)
             * (bd.Cylinder(10, 20) + bd.Pos(0, 0, 13) * bd.Cone(10, 6, 6))).wrapped
    stored = trimmed_bspline(shape)
    for face in indexed_faces(stored):
        with pytest.raises(Standard_NullObject):
            GeomConvert_SurfToAnaSurf(BRep_Tool.Surface_s(face)).ConvertToAnalytical(
                DEFAULT_TOLERANCES.freeform_fit_mm)
    exact, fitted = extract_features(shape), extract_features(stored)
    assert fitted.n_freeform_recognised == fitted.n_faces == 4
    assert [a.kind for a in fitted.axes] == ["cylinder", "cone"]
    assert_same_features(without_cone_radii(fitted),
                         without_cone_radii(replace(exact, n_freeform_recognised=4)), rel=1e-5)
    moved_shape, pose = moved(stored, 0.9, (0.3, -0.5, 0.8), (120.0, -35.5, 410.0))
    assert_same_features(without_cone_radii(extract_features(moved_shape)),
                         without_cone_radii(fitted.transformed(pose)))


def test_the_dominant_plane_direction_carries_one_and_a_half_times_the_runner_up() -> None:
    """A 10 x 20 x 30 block: the 20 x 30 faces carry twice the 10 x 30 ones (dominant); a cube
    has none; a plate with a rib across keeps the plate's normal when the rib's sides stay
    under 1/1.5 of its faces; two plates 0.8 degrees apart are one direction."""
    block = extract_features((bd.Rot(10, 20, 30) * bd.Box(10, 20, 30)).wrapped)
    assert block.dominant_plane is not None and block.principal_plane is not None
    assert abs(float(block.dominant_plane @ block.principal_plane)) == pytest.approx(1.0)
    assert block.dominant_runner_up == pytest.approx(0.5)
    cube = extract_features(bd.Box(10, 10, 10).wrapped)
    assert cube.dominant_plane is None and cube.dominant_runner_up == pytest.approx(1.0)
    ribbed = extract_features((bd.Box(60, 40, 4) + bd.Pos(0, 0, 8) * bd.Box(60, 4, 12)).wrapped)
    assert ribbed.dominant_plane is not None
    np.testing.assert_allclose(np.abs(ribbed.dominant_plane), [0, 0, 1], atol=1e-12)
    tall = extract_features((bd.Box(60, 40, 4) + bd.Pos(0, 0, 22) * bd.Box(60, 4, 40)).wrapped)
    assert tall.dominant_plane is None  # sides 2 x 60 x (40 + 4) against 2 x 60 x 40: no
    kinked = bd.Box(40, 40, 2) + bd.Pos(45, 0, 0) * bd.Rot(0, 0.8, 0) * bd.Box(40, 40, 2)
    both = extract_features(kinked.wrapped)
    assert both.dominant_plane is not None and len(both.planes) > 3
    assert both.dominant_runner_up < 0.2  # the two plates' faces are one direction


def test_ties_are_flagged_and_coaxial_faces_grouped() -> None:
    cube = extract_features(bd.Box(10, 10, 10).wrapped)
    assert cube.principal_plane_tie
    stepped = bd.Cylinder(5, 10) + bd.Pos(0, 0, 10) * bd.Cylinder(3, 10)
    f = extract_features(stepped.wrapped)
    cylinders = [a for a in f.axes if a.kind == "cylinder"]
    assert len(cylinders) == 1 and sorted(cylinders[0].radii) == pytest.approx([3, 5])
    assert not f.principal_axis_tie


def boss_on_plate() -> bd.Part:
    """A plate with a filleted boss and a spherical pocket: a torus and a sphere inside."""
    part = bd.Box(40, 40, 5) + bd.Pos(0, 0, 7.5) * bd.Cylinder(5, 10)
    foot = part.edges().filter_by(bd.GeomType.CIRCLE).sort_by(bd.Axis.Z)[0]
    return bd.fillet([foot], 2) - bd.Pos(10, 10, 0) * bd.Sphere(1.5)


@pytest.mark.parametrize("make", [
    boss_on_plate,
    lambda: bd.fillet((bd.Box(30, 20, 10) - bd.Cylinder(4, 10)).edges(), 1.5),  # spheres too
    lambda: bd.fillet(bd.Cylinder(8, 20).edges(), 2) + bd.Pos(0, 0, 12) * bd.Sphere(5),
    lambda: bd.Torus(12, 3) - bd.Pos(12, 0, 0) * bd.Box(10, 40, 10),
    lambda: bd.Pos(40, -7, 3) * bd.Rot(20, 35, 50) * bd.fillet(bd.Cylinder(6, 9).edges(), 1),
])
def test_tight_bbox_equals_occts_optimal_box(make) -> None:  # type: ignore[no-untyped-def]
    shape = make().wrapped
    assert_bbox_is_occts(shape)
    assert_bbox_is_occts(BRepBuilderAPI_NurbsConvert(shape, True).Shape())  # B-spline faces


@pytest.mark.parametrize("make", [
    boss_on_plate,
    lambda: bd.fillet((bd.Box(30, 20, 10) - bd.Cylinder(4, 10)).edges(), 1.5),
    lambda: bd.Pos(40, -7, 3) * bd.Rot(20, 35, 50) * bd.fillet(bd.Cylinder(6, 9).edges(), 1),
    lambda: bd.Rot(10, 70, 0) * bd.Sphere(4),
])
def test_a_whole_torus_or_sphere_patch_is_boxed_exactly(make) -> None:  # type: ignore[no-untyped-def]
    faces = exact_round_faces(make().wrapped)
    assert faces
    for face in faces:
        lo, hi, _ = features_module._hull_box(face)
        points = face_samples(face)
        # It holds every point, and the grid (spacing h) reaches it within its sag (~h^2).
        assert np.all(points.min(axis=0) >= lo - 1e-9) and np.all(points.max(axis=0) <= hi + 1e-9)
        size = float(np.max(hi - lo))
        assert np.allclose(points.min(axis=0), lo, rtol=0, atol=1e-4 * size)
        assert np.allclose(points.max(axis=0), hi, rtol=0, atol=1e-4 * size)


def test_tight_bbox_skips_costly_faces_that_cannot_count(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    boxed = []
    optimal_box = features_module._optimal_box
    monkeypatch.setattr(features_module, "_optimal_box",
                        lambda shape: boxed.append(shape) or optimal_box(shape))
    shape = boss_on_plate().wrapped
    tight_bbox(shape)
    assert len(boxed) == len(indexed_faces(shape)) - 2  # the fillet and the pocket


def test_given_mass_properties_change_nothing() -> None:
    shape = bd.fillet(bd.Box(12, 8, 6).edges(), 1).wrapped
    integrals = part_integrals(shape, indexed_faces(shape), MASS_PROPS_REL_EPS)
    given, computed = extract_features(shape, integrals=integrals), extract_features(shape)
    assert given.to_dict() == computed.to_dict()
    assert (given.volume, *given.centroid) == (integrals.volume, *integrals.centroid)
    volume, centroid = brep_mass(shape)  # OpenCascade's own integration of the whole solid
    assert given.volume == pytest.approx(volume, rel=1e-9)
    assert np.allclose(given.centroid, centroid, rtol=0, atol=1e-9)


def test_features_round_trip_through_workspace(tmp_path: Path) -> None:
    f = extract_features((bd.Box(8, 8, 4) - bd.Cylinder(2, 4)).wrapped)
    write_features(tmp_path / "f.json", f)
    back = read_features(tmp_path / "f.json")
    assert back.to_dict() == f.to_dict()


# ---------------------------------------------------------------- real files


@pytest.mark.shared
@pytest.mark.parametrize("name", ["kcl_socket-head-cap-screw.step", "occt_xr1-tc-blt.stp"])
def test_bolt_principal_axis_is_its_shank(step_solids, name: str) -> None:
    f = extract_features(step_solids(f"fasteners/{name}")[0])
    along, gap = axis_check(f, "longest")
    assert along >= COS_1_DEG
    assert gap <= 0.01 * float(np.linalg.norm(f.bbox_max - f.bbox_min))


@pytest.mark.shared
@pytest.mark.parametrize("name", ["kcl_hex-nut.step", "occt_xr1-tc-nut.stp"])
def test_nut_principal_axis_is_its_bore(step_solids, name: str) -> None:
    f = extract_features(step_solids(f"fasteners/{name}")[0])
    along, gap = axis_check(f, "thinnest")
    assert along >= COS_1_DEG
    # kcl_hex-nut's hexagon is slightly irregular: its centroid sits 0.16 mm off the bore.
    assert gap <= 0.02 * float(np.linalg.norm(f.bbox_max - f.bbox_min))


@pytest.mark.shared
@pytest.mark.parametrize("name", [AS1, "linear-rotary-motion/kcl_ball-bearing.step",
                                  "abc-misc/abc_00003455.step"])
def test_tight_bbox_equals_occts_optimal_box_on_real_parts(step_solids, name: str) -> None:
    for solid in step_solids(name):
        assert_bbox_is_occts(solid)


@pytest.mark.shared
def test_tight_bbox_holds_fillets_that_occts_optimal_box_cuts(step_solids) -> None:
    """Two fillets of this part poke out of OpenCascade's optimal box by up to 4.2e-5 mm."""
    short = 0.0
    for solid in step_solids("assemblies/abc_00509765.step"):
        lo, hi = tight_bbox(solid)
        occt = np.array(occt_optimal_box(solid))
        for face in exact_round_faces(solid):
            points = face_samples(face)
            assert np.all(points.min(axis=0) >= lo - 1e-9)
            assert np.all(points.max(axis=0) <= hi + 1e-9)
            short = max(short, float(np.max(occt[:3] - points.min(axis=0))),
                        float(np.max(points.max(axis=0) - occt[3:])))
    assert short > 1e-5  # what OpenCascade's own box misses


@pytest.mark.shared
def test_cax_if_bspline_cylinders_are_recognised(step_solids) -> None:
    """The AS1 assembly stores every cylinder as a B-spline: all must still be found."""
    solids = step_solids(AS1)
    bolts, nuts = [], []
    for solid in solids:
        f = extract_features(solid)
        n_bspline = sum(
            BRepAdaptor_Surface(face).GetType() == GeomAbs_BSplineSurface
            for face in indexed_faces(solid)
        )
        assert f.n_freeform_recognised == n_bspline > 0
        assert f.principal_axis is not None
        extent = sorted(np.round(f.bbox_max - f.bbox_min, 3))
        if extent == [15, 15, 37]:
            bolts.append(f)
        elif extent == [3, 15, 20]:
            nuts.append(f)
    assert bolts and nuts
    for f in bolts:
        assert axis_check(f, "longest") == (pytest.approx(1.0), pytest.approx(0.0, abs=1e-3))
    for f in nuts:
        assert axis_check(f, "thinnest") == (pytest.approx(1.0), pytest.approx(0.0, abs=1e-3))


@pytest.mark.shared
def test_kcl_pipe_bevel_cones_are_recognised(step_solids) -> None:
    """The pipe of the KCL flange assembly: four 30 degree B-spline bevel cones on which OCCT's
    converter raises, between plain cylinders of radii 9.271 to 18.796 on the Z axis."""
    solids = step_solids("assemblies/kcl_pipe-flange-assembly.step")
    pipe = next(s for s in solids if extract_features(s).bbox_max[2] > 80)
    faces = indexed_faces(pipe)
    found = recognise_faces(faces)
    assert len(found) == len(faces) == 13
    cones = [p for p in found if p.kind == CONE]
    assert len(cones) == 4 and all(p.freeform for p in cones)
    for p in cones:
        assert abs(p.direction[2]) == pytest.approx(1.0, abs=1e-12)
        assert np.linalg.norm(p.point[:2]) <= 1e-9
    assert sorted(round(p.radius, 3) for p in found if p.kind == "cylinder") == [
        9.271, 12.446, 12.446, 15.621, 15.621, 18.796, 18.796]


@pytest.mark.shared
@pytest.mark.parametrize("part", [
    "fasteners/occt_xr1-tc-nut.stp",
    "fasteners/kcl_socket-head-cap-screw.step",
    "linear-rotary-motion/spot_Front_Driveshaft.step",
    AS1 + "#3",
])
def test_features_are_equivariant_under_rigid_motion(step_solids, part: str) -> None:
    path, _, index = part.partition("#")
    solid = step_solids(path)[int(index or 0)]
    base = extract_features(solid, DEFAULT_TOLERANCES)
    shape, pose = moved(solid, 0.9, (0.3, -0.5, 0.8), (120.0, -35.5, 410.0))
    got, want = extract_features(shape), base.transformed(pose)
    assert_same_features(got, want)
    assert np.all(got.bbox_min >= want.bbox_min - 1e-6)
    assert np.all(got.bbox_max <= want.bbox_max + 1e-6)
    # A quarter turn maps the axis-aligned box onto the moved part's box exactly.
    shape, pose = moved(solid, np.pi / 2, (0, 0, 1), (-7.0, 3.0, 11.0))
    got, want = extract_features(shape), base.transformed(pose)
    np.testing.assert_allclose(got.bbox_min, want.bbox_min, atol=1e-6)
    np.testing.assert_allclose(got.bbox_max, want.bbox_max, atol=1e-6)
