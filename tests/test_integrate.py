"""Tests of cadio.cad.integrate and cadio.cad.solid_props: face integrals against OpenCascade."""

from __future__ import annotations

from pathlib import Path

import build123d as bd
import numpy as np
import pytest
from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert

from cadio.cad.faces import indexed_faces
from cadio.cad.integrate import AREA, AREA_MOMENT, VOLUME, VOLUME_MOMENT, face_integrals
from cadio.cad.solid_props import (
    _occt_terms,
    _vertex_mean,
    part_integrals,
    prefer_numpy,
    summed,
)
from cadio.cad.step import read_step
from cadio.cad.tessellate import MASS_PROPS_REL_EPS, brep_mass


def _nurbs(shape: bd.Shape) -> object:
    return BRepBuilderAPI_NurbsConvert(shape.wrapped, True).Shape()


def _assert_terms_close(ours: np.ndarray, occt: np.ndarray, size: float) -> None:
    area = occt[AREA]
    assert ours[AREA] == pytest.approx(area, rel=1e-7)
    assert np.allclose(ours[AREA_MOMENT], occt[AREA_MOMENT], rtol=0, atol=1e-7 * area * size)
    assert ours[VOLUME] == pytest.approx(occt[VOLUME], rel=1e-7, abs=1e-7 * area * size)
    assert np.allclose(ours[VOLUME_MOMENT], occt[VOLUME_MOMENT], rtol=0,
                       atol=1e-7 * area * size * size)


@pytest.mark.parametrize("build", [
    lambda: bd.Pos(30, -20, 5) * bd.fillet(bd.Box(20, 12, 8).edges(), 2),
    lambda: bd.Pos(-7, 3, 40) * bd.Cylinder(6, 15),  # periodic in u, a seam on the face
    lambda: bd.Cone(8, 3, 12) - bd.Cylinder(2, 12),  # a face with a hole: two wires
    lambda: bd.Pos(5, 5, 5) * bd.Sphere(9),  # degenerate edges at the poles
    lambda: bd.Torus(10, 3),
], ids=["filleted box", "cylinder", "holed cone", "sphere", "torus"])
def test_every_face_of_a_nurbs_solid_matches_occt(build) -> None:  # type: ignore[no-untyped-def]
    """Each face converted to a rational B-spline: area, its centroid, and the volume cone
    terms about one point agree to 1e-7 with the same face before conversion (planes,
    cylinders, cones, spheres, tori, where OpenCascade's rule is exact; on the converted faces
    it is off by up to 3e-6)."""
    solid = build()
    shape = _nurbs(solid)
    origin = _vertex_mean(shape)
    box = solid.bounding_box()
    size = float(np.abs(np.array([*box.min, *box.max]).reshape(2, 3) - origin).max())
    faces = indexed_faces(shape)
    analytic = indexed_faces(solid.wrapped)  # the conversion keeps the faces and their order
    assert len(faces) == len(analytic)
    total = np.zeros(8)
    for face, exact in zip(faces, analytic, strict=True):
        ours = face_integrals(face, origin)
        assert ours is not None
        _assert_terms_close(ours, _occt_terms(exact, origin, MASS_PROPS_REL_EPS), size)
        total += ours
    volume, centroid = brep_mass(solid.wrapped)
    assert total[VOLUME] == pytest.approx(volume, rel=1e-7)
    assert np.allclose(origin + total[VOLUME_MOMENT] / total[VOLUME], centroid, atol=1e-6)


def test_face_integrals_decline_other_surfaces() -> None:
    box = bd.Box(3, 4, 5).wrapped
    assert all(face_integrals(f) is None and not prefer_numpy(f) for f in indexed_faces(box))


def _vinert(face: object, origin: np.ndarray) -> tuple[float, np.ndarray]:
    """OpenCascade's volume and first moment of the cone from ``origin`` over ``face``."""
    from OCP.BRepGProp import BRepGProp_Domain, BRepGProp_Face, BRepGProp_Vinert
    from OCP.gp import gp_Pnt

    cone = BRepGProp_Vinert()
    cone.SetLocation(gp_Pnt(*origin))
    cone.Perform(BRepGProp_Face(face, True), BRepGProp_Domain(face), MASS_PROPS_REL_EPS)
    c = cone.CentreOfMass()
    return cone.Mass(), cone.Mass() * (np.array([c.X(), c.Y(), c.Z()]) - origin)


def test_a_plane_face_volume_terms_follow_from_its_area_moments() -> None:
    """Planes skip OpenCascade's volume integration; their cone terms must be the same."""
    shape = (bd.Pos(4, -9, 2) * bd.Rot(20, 30, 40) * bd.Box(7, 5, 3)).wrapped
    origin = np.array([1.0, 2.0, -3.0])
    for face in indexed_faces(shape):
        terms = _occt_terms(face, origin, MASS_PROPS_REL_EPS)
        volume, moment = _vinert(face, origin)
        assert terms[VOLUME] == pytest.approx(volume, rel=1e-9, abs=1e-9)
        assert np.allclose(terms[VOLUME_MOMENT], moment, atol=1e-8)


@pytest.mark.parametrize("build", [
    # a tube, tilted and moved: its outer face points away from the axis, its bore towards it
    lambda: bd.Pos(30, -5, 12) * bd.Rot(25, -40, 10) * (bd.Cylinder(6, 14) - bd.Cylinder(2.5, 14)),
    # a half ball with a spherical cavity (a sphere face turned inwards) off its centre
    lambda: bd.Pos(-7, 3, 20) * ((bd.Sphere(9) - bd.Sphere(3))
                                 & bd.Pos(0, 0, 5) * bd.Box(30, 30, 20)),
])
def test_cylinder_and_sphere_volume_terms_follow_from_their_area_moments(  # type: ignore[no-untyped-def]
        build) -> None:
    """Cylinders and spheres skip OpenCascade's volume integration too: their cone terms come
    from the area, centroid and inertia matrix, on faces of either orientation."""
    shape = build().wrapped
    origin = _vertex_mean(shape) + np.array([1.5, -2.0, 0.7])
    for face in indexed_faces(shape):
        terms = _occt_terms(face, origin, MASS_PROPS_REL_EPS)
        volume, moment = _vinert(face, origin)
        scale = terms[AREA] * 40.0  # area times the reach of these parts, mm^3
        assert abs(terms[VOLUME] - volume) < 1e-8 * scale
        assert np.allclose(terms[VOLUME_MOMENT], moment,
                           atol=1e-8 * scale * 40.0)
    volume, centroid = brep_mass(shape)
    integrals = part_integrals(shape, indexed_faces(shape), MASS_PROPS_REL_EPS)
    assert integrals.volume == pytest.approx(volume, rel=1e-9)
    assert np.allclose(integrals.centroid, centroid, atol=1e-8)


@pytest.mark.shared
@pytest.mark.parametrize("name", ["abc_00001511.step", "abc_00003487.step"])
def test_real_parts_with_many_span_faces(shared_step_dir: Path, name: str) -> None:
    """The real faces this module exists for (rational, 67-212 knot spans): integrated here,
    and the part's volume and centroid are those of OpenCascade's terms of every face (which
    sum to its ``VolumeProperties``, as the volume-term tests above check; on these parts its
    adaptive rule over the whole solid takes 3-9 s more)."""
    path = next(shared_step_dir.rglob(name))
    shape = read_step(path)[0].shape
    faces = indexed_faces(shape)
    origin = _vertex_mean(shape)
    occt = [_occt_terms(face, origin, MASS_PROPS_REL_EPS) for face in faces]
    picked = [k for k, face in enumerate(faces) if prefer_numpy(face)]
    assert picked
    for k in picked:
        ours = face_integrals(faces[k], origin)
        assert ours is not None
        _assert_terms_close(ours, occt[k], 100.0)
    result = part_integrals(shape, faces, MASS_PROPS_REL_EPS)
    theirs = summed(origin, occt)
    assert result.volume == pytest.approx(theirs.volume, rel=1e-7)
    assert np.allclose(result.centroid, theirs.centroid, atol=1e-6)


@pytest.mark.shared
def test_rational_faces_whose_weights_spread_widely_are_integrated_here(
        shared_step_dir: Path) -> None:
    """spot_Dogbone face 15, a rational bicubic patch with weights spread 9:1: OpenCascade's
    adaptive rule at eps 1e-6 gives 135.804835 mm^2, converging on 135.952025 as its eps
    shrinks (135.946371 at 1e-8, 135.953111 at 1e-10); the part's areas are ours."""
    path = shared_step_dir / "brakes-clutches-couplings" / "spot_Dogbone.step"
    shape = read_step(path)[0].shape
    faces = indexed_faces(shape)
    assert prefer_numpy(faces[15])
    area, _ = part_integrals(shape, faces, MASS_PROPS_REL_EPS).face_props[15]
    assert area == pytest.approx(135.952025, abs=2e-6)
    assert _occt_terms(faces[15], _vertex_mean(shape), MASS_PROPS_REL_EPS)[AREA] == \
        pytest.approx(135.804835, abs=2e-6)


@pytest.mark.parametrize("build", [lambda: bd.Cylinder(6, 15), lambda: bd.Sphere(5),
                                   lambda: bd.Torus(10, 3)], ids=["cylinder", "sphere", "torus"])
def test_rational_faces_with_close_weights_stay_with_opencascade(build) -> None:  # type: ignore[no-untyped-def]
    """Quadrics as NURBS: rational with few spans, weights spread 2:1 (cylinder), 2.8:1
    (sphere) and exactly 4:1 (torus: not more than the limit)."""
    from OCP.BRep import BRep_Tool
    from OCP.GeomAdaptor import GeomAdaptor_Surface

    faces = indexed_faces(_nurbs(build()))
    surfaces = [GeomAdaptor_Surface(BRep_Tool.Surface_s(f)) for f in faces]
    assert any(a.IsURational() or a.IsVRational() for a in surfaces)
    assert not any(prefer_numpy(f) for f in faces)


def test_an_instance_of_a_shared_solid_is_the_first_moved() -> None:
    """Two placements of one B-rep: the second is not integrated again, and its integrals
    are those of integrating it in place."""
    from cadio.cad.solid_props import InstanceIntegrals

    base = bd.fillet(bd.Box(12, 8, 6).edges(), 1) - bd.Cylinder(2, 6)
    placed = [base.wrapped, (bd.Pos(40, -3, 7) * bd.Rot(10, 70, -25) * base).wrapped]
    assert placed[1].IsPartner(placed[0])
    instances = InstanceIntegrals(MASS_PROPS_REL_EPS)
    for shape in placed:
        ours = instances(shape)
        fresh = part_integrals(shape, indexed_faces(shape), MASS_PROPS_REL_EPS)
        assert ours.volume == pytest.approx(fresh.volume, rel=1e-12)
        assert np.allclose(ours.centroid, fresh.centroid, atol=1e-9)
        for (a, c), (b, d) in zip(ours.face_props, fresh.face_props, strict=True):
            assert a == pytest.approx(b, rel=1e-12) and np.allclose(c, d, atol=1e-9)
    assert len(instances._seen) == 1
