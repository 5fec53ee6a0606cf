"""A solid's volume, volume centroid and per-face areas from its exact B-rep, each face once.

Each face goes by one of two routes (``prefer_numpy``): the NumPy quadrature of
``cadio.cad.integrate`` for rational B-spline faces where OpenCascade's adaptive rule is slow
or its eps no bound, OpenCascade's adaptive rule (``BRepGProp``) for the others, with the
volume terms of planes, cylinders and spheres in closed form from their area and moments.
``InstanceIntegrals`` integrates a B-rep placed many times in an assembly once.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepGProp import BRepGProp, BRepGProp_Domain, BRepGProp_Face, BRepGProp_Vinert
from OCP.GeomAbs import GeomAbs_BSplineSurface, GeomAbs_Cylinder, GeomAbs_Plane, GeomAbs_Sphere
from OCP.GeomAdaptor import GeomAdaptor_Surface
from OCP.gp import gp_Pnt
from OCP.GProp import GProp_GProps
from OCP.TopAbs import TopAbs_REVERSED, TopAbs_VERTEX
from OCP.TopExp import TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Iterator, TopoDS_Shape

from cadio.cad.faces import indexed_faces
from cadio.cad.integrate import AREA, AREA_MOMENT, VOLUME, VOLUME_MOMENT, face_integrals
from cadio.cad.step import location_matrix
from cadio.records import FloatArray

# Knots in one direction from which a rational B-spline face goes to ``face_integrals``.
MANY_SPANS = 60
# Rational faces whose weights spread more than this (largest over smallest) go there
# too: OpenCascade's adaptive eps 1e-6 misses their area by up to 1.1e-3 (weights spread
# 9:1), while every real face it integrates within 1e-6 spreads at most 3.7:1
# (``bench/speed/integrals.py``).
WEIGHT_SPREAD = 4.0


@dataclass(frozen=True)
class PartIntegrals:
    """Volume and volume centroid of a solid, and the area and area centroid of each face."""

    volume: float
    centroid: FloatArray
    face_props: tuple[tuple[float, FloatArray], ...]


    def moved(self, rotation: FloatArray, translation: FloatArray) -> PartIntegrals:
        """The same solid after the rigid motion x -> rotation @ x + translation."""
        return PartIntegrals(
            volume=self.volume, centroid=rotation @ self.centroid + translation,
            face_props=tuple((a, rotation @ c + translation) for a, c in self.face_props))


class InstanceIntegrals:
    """``part_integrals`` of the solids of one file, each shared B-rep integrated once.

    An assembly places one solid many times (the balls of a bearing, a screw used six
    times): each is the same B-rep (TShape) under another location, so its integrals are
    the first instance's moved rigidly, not integrated again.
    """

    def __init__(self, eps: float) -> None:
        self.eps = eps
        self._seen: list[tuple[TopoDS_Shape, FloatArray, PartIntegrals]] = []

    def __call__(self, shape: TopoDS_Shape) -> PartIntegrals:
        bare = shape.Located(TopLoc_Location())
        place = location_matrix(shape.Location())
        for other, other_place, integrals in self._seen:
            if bare.IsEqual(other):
                motion = place @ np.linalg.inv(other_place)
                rotation = motion[:3, :3]
                if np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-12) and \
                        np.linalg.det(rotation) > 0:
                    return integrals.moved(rotation, motion[:3, 3])
                break
        result = part_integrals(shape, indexed_faces(shape), self.eps)
        self._seen.append((bare, place, result))
        return result


def prefer_numpy(face: TopoDS_Face) -> bool:
    """Whether ``face_integrals`` is the route for a face: a rational B-spline with many spans
    in one direction, where OpenCascade's adaptive rule takes up to seconds, or whose weights
    spread more than ``WEIGHT_SPREAD``, where its eps is no bound (non-rational faces, and
    rational ones with few spans and close weights, it integrates in milliseconds and within
    its eps)."""
    adaptor = GeomAdaptor_Surface(BRep_Tool.Surface_s(face))
    if adaptor.GetType() != GeomAbs_BSplineSurface:
        return False
    if not (adaptor.IsURational() or adaptor.IsVRational()):
        return False
    if max(adaptor.NbUKnots(), adaptor.NbVKnots()) >= MANY_SPANS:
        return True
    weights = adaptor.BSpline().Weights()
    values = [weights.Value(i, j) for i in range(weights.LowerRow(), weights.UpperRow() + 1)
              for j in range(weights.LowerCol(), weights.UpperCol() + 1)]
    return bool(max(values) > WEIGHT_SPREAD * min(values))


def part_integrals(shape: TopoDS_Shape, faces: Sequence[TopoDS_Face], eps: float
                   ) -> PartIntegrals:
    """Volume, volume centroid and per-face area and area centroid, each face integrated once.

    Faces ``prefer_numpy`` picks go through ``face_integrals`` (OpenCascade's adaptive rule
    where it declines); the others through OpenCascade's adaptive rule with relative
    ``eps``, for the area (``BRepGProp.SurfaceProperties``) and the volume term
    (``BRepGProp_Vinert`` about the mean of the vertices, as ``BRepGProp.VolumeProperties``
    does), except that the volume terms of a plane, cylinder or sphere follow from its area,
    centroid and (for the last two) inertia matrix.

    Args:
        shape: a solid (or compound of solids), mm.
        faces: ``indexed_faces(shape)``.
        eps: OpenCascade's relative accuracy.

    Returns:
        PartIntegrals; face_props in the order of ``faces``.
    """
    origin = _vertex_mean(shape)
    terms = []
    for face in faces:
        got = face_integrals(face, origin) if prefer_numpy(face) else None
        terms.append(_occt_terms(face, origin, eps) if got is None else got)
    return summed(origin, terms)


def summed(origin: FloatArray, terms: Iterable[FloatArray]) -> PartIntegrals:
    """A solid's integrals from the eight terms of each of its faces, taken about ``origin``."""
    volume, moment = 0.0, np.zeros(3)
    props = []
    for face_terms in terms:
        area = float(face_terms[AREA])
        props.append((area, origin + face_terms[AREA_MOMENT] / area if area > 0
                      else origin.copy()))
        volume += float(face_terms[VOLUME])
        moment += face_terms[VOLUME_MOMENT]
    centroid = origin + moment / volume if volume != 0 else origin.copy()
    return PartIntegrals(volume=volume, centroid=centroid, face_props=tuple(props))


def _vertex_mean(shape: TopoDS_Shape) -> FloatArray:
    explorer = TopExp_Explorer(shape, TopAbs_VERTEX)
    points = []
    while explorer.More():
        p = BRep_Tool.Pnt_s(TopoDS.Vertex_s(explorer.Current()))
        points.append((p.X(), p.Y(), p.Z()))
        explorer.Next()
    return np.mean(points, axis=0) if points else np.zeros(3)


def _occt_terms(face: TopoDS_Face, origin: FloatArray, eps: float) -> FloatArray:
    """The eight integrals of one face (about ``origin``) by OpenCascade's adaptive rule."""
    out = np.zeros(8)
    sprops = GProp_GProps()
    BRepGProp.SurfaceProperties_s(face, sprops, eps)
    area = sprops.Mass()
    c = sprops.CentreOfMass()
    rel = np.array([c.X(), c.Y(), c.Z()]) - origin
    out[AREA], out[AREA_MOMENT] = area, area * rel
    surface = GeomAdaptor_Surface(BRep_Tool.Surface_s(face))
    if surface.GetType() == GeomAbs_Plane:
        # The cone from the origin over a plane face has the constant height h = n . c:
        # volume h A / 3, first moment h A c / 4 (c about the origin).
        pos = surface.Plane().Position()
        n = np.cross(_xyz(pos.XDirection()), _xyz(pos.YDirection()))
        if face.Orientation() == TopAbs_REVERSED:
            n = -n
        height = float(n @ rel)
        out[VOLUME] = height * area / 3.0
        out[VOLUME_MOMENT] = height * area * rel / 4.0
        return out
    if surface.GetType() in (GeomAbs_Cylinder, GeomAbs_Sphere):
        _round_volume_terms(surface, face, sprops, origin, out)
        return out
    vprops = BRepGProp_Vinert()
    vprops.SetLocation(gp_Pnt(*origin))
    bface = BRepGProp_Face(face, True)
    if TopoDS_Iterator(face).More():
        vprops.Perform(bface, BRepGProp_Domain(face), eps)
    else:
        vprops.Perform(bface, eps)
    mass = vprops.Mass()
    vc = vprops.CentreOfMass()
    out[VOLUME] = mass
    out[VOLUME_MOMENT] = mass * (np.array([vc.X(), vc.Y(), vc.Z()]) - origin)
    return out


def _round_volume_terms(surface: GeomAdaptor_Surface, face: TopoDS_Face, sprops: GProp_GProps,
                        origin: FloatArray, out: FloatArray) -> None:
    """A cylinder's or sphere's volume terms from its area, centroid and inertia matrix.

    The face's normal is n = sigma P (S - O) / R, P projecting out the axis (the identity for a
    sphere, O its centre), sigma = +1 where it points away from the axis. With d = P (O - o)
    (o the origin), (S - o) . n = sigma (R^2 + d . (S - O)) / R, so the cone from o over the face
    has volume sigma A (R^2 + d . (c - O)) / (3 R) and first moment
    sigma (R^2 A (c - o) + (C + A (c - o)(c - O)^T) d) / (4 R), where A, c and C are the face's
    area, centroid and second central moments (C = tr(I) / 2 - I from its inertia matrix I).
    """
    if surface.GetType() == GeomAbs_Cylinder:
        cylinder = surface.Cylinder()
        radius, pos = cylinder.Radius(), cylinder.Position()
        axis = _xyz(pos.Direction())
        project = np.eye(3) - np.outer(axis, axis)
    else:
        sphere = surface.Sphere()
        radius, pos = sphere.Radius(), sphere.Position()
        project = np.eye(3)
    centre = _xyz(pos.Location())
    # The natural normal S_u x S_v points away from the axis on a right-handed position.
    sigma = 1.0 if np.cross(_xyz(pos.XDirection()), _xyz(pos.YDirection())) @ \
        _xyz(pos.Direction()) > 0 else -1.0
    if face.Orientation() == TopAbs_REVERSED:
        sigma = -sigma
    area = sprops.Mass()
    c = sprops.CentreOfMass()
    c = np.array([c.X(), c.Y(), c.Z()])
    m = sprops.MatrixOfInertia()
    inertia = np.array([[m.Value(i, j) for j in (1, 2, 3)] for i in (1, 2, 3)])
    second = np.trace(inertia) / 2.0 * np.eye(3) - inertia
    d = project @ (centre - origin)
    out[VOLUME] = sigma * area * (radius**2 + d @ (c - centre)) / (3.0 * radius)
    out[VOLUME_MOMENT] = sigma * (radius**2 * area * (c - origin)
                                  + (second + area * np.outer(c - origin, c - centre)) @ d
                                  ) / (4.0 * radius)


def _xyz(d: Any) -> FloatArray:
    return np.array([d.X(), d.Y(), d.Z()])
