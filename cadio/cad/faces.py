"""Recognition of B-rep faces as planes, cylinders and cones, with stable face ids.

Features (``cadio.cad.features``) and face-level mates (``cadio.truth.mates``) both reason on
primitive faces. Analytic faces are taken as stored; freeform faces (B-spline, Bezier, surfaces of
revolution or extrusion, offset and trimmed surfaces) are converted with OpenCascade's
``GeomConvert_SurfToAnaSurf`` (and ``GeomLib_IsPlanarSurface``) when they fit a primitive within
``Tolerances.freeform_fit_mm``: real files store many planes and cylinders as B-splines (the
CAx-IF AS1 assembly stores every cylinder so), and missing them would silently drop mates. Where
the converter raises (some B-spline cones and cylinders), the face is sampled and fitted by least
squares (``cadio.cad.surface_fit``) within the same tolerance.

Face ids are 0-based positions in ``TopExp.MapShapes_s(shape, TopAbs_FACE, ...)`` order, stable
for a given shape and unchanged by a rigid motion (see ``indexed_faces``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Surface
from OCP.BRepGProp import BRepGProp, BRepGProp_Face
from OCP.BRepTools import BRepTools
from OCP.Geom import Geom_ConicalSurface, Geom_CylindricalSurface, Geom_Plane, Geom_Surface
from OCP.GeomAbs import GeomAbs_Cone, GeomAbs_Cylinder, GeomAbs_Plane, GeomAbs_Sphere, GeomAbs_Torus
from OCP.GeomConvert import GeomConvert_SurfToAnaSurf
from OCP.GeomLib import GeomLib_IsPlanarSurface
from OCP.gp import gp_Ax1, gp_Ax3, gp_Cone, gp_Cylinder, gp_Dir, gp_Pln, gp_Pnt, gp_Vec
from OCP.GProp import GProp_GProps
from OCP.TopAbs import TopAbs_FACE
from OCP.TopExp import TopExp
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape
from OCP.TopTools import TopTools_IndexedMapOfShape

from cadio.cad.surface_fit import fit_primitive
from cadio.cad.tessellate import MASS_PROPS_REL_EPS
from cadio.errors import GeometryError
from cadio.records import FloatArray
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances

PLANE, CYLINDER, CONE = "plane", "cylinder", "cone"
# Parameter bounds beyond this are OCCT's "infinite" (2e100): such surfaces are fitted per face.
_FINITE = 1e99
# Where the converter raises, the face is fitted on a grid of _FIT_GRID x _FIT_GRID parameter values
# (45 degree steps round a whole cone); samples with |du x dv| < _SINGULAR (poles) are skipped.
_FIT_GRID, _SINGULAR = 9, 1e-9


@dataclass(frozen=True)
class FacePrimitive:
    """One face recognised as a plane, cylinder or cone, in the shape's coordinates.

    face_id: 0-based index in ``indexed_faces`` order. area: mm^2.
    direction: (3,) unit: the plane's normal or the axis direction (sign as found).
    point: (3,) mm: for a plane its area centroid; for a cylinder or cone the projection of
    the face's area centroid on the axis (a point near the face, so it moves with the part).
    radius: mm (cone: reference radius; plane: 0). outward: (3,) unit outward normal of a
    planar face (face orientation applied), zeros otherwise.
    freeform: True when the face's surface was not stored as this primitive.
    """

    face_id: int
    kind: str
    area: float
    direction: FloatArray
    point: FloatArray
    radius: float
    outward: FloatArray
    freeform: bool


def indexed_faces(shape: TopoDS_Shape) -> list[TopoDS_Face]:
    """The faces of ``shape``; list position i is face id i (OCCT's map index i + 1).

    Args:
        shape: any shape.

    Returns:
        Faces in ``TopExp.MapShapes_s`` order, each once.
    """
    face_map = TopTools_IndexedMapOfShape()
    TopExp.MapShapes_s(shape, TopAbs_FACE, face_map)
    return [TopoDS.Face_s(face_map.FindKey(i)) for i in range(1, face_map.Extent() + 1)]


def face_area(face: TopoDS_Face) -> float:
    """Area of one face, mm^2."""
    return surface_props(face)[0]


def surface_props(face: TopoDS_Face) -> tuple[float, FloatArray]:
    """(area mm^2, area centroid (3,) mm) of one face."""
    props = GProp_GProps()
    BRepGProp.SurfaceProperties_s(face, props, MASS_PROPS_REL_EPS)
    return float(props.Mass()), _xyz(props.CentreOfMass())


def recognise_faces(
    faces: Sequence[TopoDS_Face],
    tol: Tolerances = DEFAULT_TOLERANCES,
    props: Sequence[tuple[float, FloatArray]] | None = None,
) -> list[FacePrimitive]:
    """Recognise each face as a plane, cylinder or cone where it is (or fits) one.

    Args:
        faces: faces in id order (``indexed_faces``).
        tol: ``freeform_fit_mm`` is the largest deviation accepted for a freeform face.
        props: per face (area mm^2, area centroid (3,) mm) when already known.

    Returns:
        The recognised faces, in id order; spheres, tori and true freeform faces are absent.
    """
    found = []
    for i, face in enumerate(faces):
        prim = _recognise(face, tol.freeform_fit_mm)
        if prim is None:
            continue
        kind, geom, freeform = prim
        area, centre = surface_props(face) if props is None else props[i]
        found.append(_describe(i, face, kind, geom, area, centre, freeform))
    return found


def _recognise(face: TopoDS_Face, fit_mm: float) -> tuple[str, Any, bool] | None:
    """(kind, gp primitive, freeform) for a face, or None when it is none of the three."""
    adaptor = BRepAdaptor_Surface(face, True)
    kind = adaptor.GetType()
    if kind == GeomAbs_Plane:
        return PLANE, adaptor.Plane(), False
    if kind == GeomAbs_Cylinder:
        return CYLINDER, adaptor.Cylinder(), False
    if kind == GeomAbs_Cone:
        return CONE, adaptor.Cone(), False
    if kind in (GeomAbs_Sphere, GeomAbs_Torus):
        return None
    return _fit_freeform(face, fit_mm)


def _fit_freeform(face: TopoDS_Face, fit_mm: float) -> tuple[str, Any, bool] | None:
    """Convert a freeform face's surface to a plane, cylinder or cone within ``fit_mm``."""
    surface = BRep_Tool.Surface_s(face)  # a located copy: already in the shape's coordinates
    try:
        analytic = _convert(surface, _face_domain(face, surface), fit_mm)
        if analytic is None and max(map(abs, surface.Bounds())) < _FINITE:
            analytic = _convert(surface, None, fit_mm)  # the whole surface fitting, the face fits
    except Exception:  # OCP's Standard_* exceptions share no Python base class but Exception
        # The converter raises on some B-spline cones and cylinders (Standard_NullObject; the
        # KCL pipe's bevelled ends) and on degenerate patches (a sphere's poles): fit samples.
        return _fit_sampled(face, surface, fit_mm)
    if analytic is not None:
        if isinstance(analytic, Geom_Plane):
            return PLANE, analytic.Pln(), True
        if isinstance(analytic, Geom_CylindricalSurface):
            return CYLINDER, analytic.Cylinder(), True
        if isinstance(analytic, Geom_ConicalSurface):
            return CONE, analytic.Cone(), True
        return None  # a sphere or torus
    planar = GeomLib_IsPlanarSurface(surface, fit_mm)
    if planar.IsPlanar():
        return PLANE, planar.Plan(), True
    return None


def _fit_sampled(face: TopoDS_Face, surface: Geom_Surface, fit_mm: float
                 ) -> tuple[str, Any, bool] | None:
    """A plane, cylinder or cone fitted by least squares to the face sampled on a UV grid.

    Every grid point of the face's parameter box must lie within ``fit_mm``, as the converter
    requires of its own samples; points where the surface is singular (a pole) are skipped.
    """
    umin, umax, vmin, vmax = _face_domain(face, surface)
    points, normals = [], []
    for u in np.linspace(umin, umax, _FIT_GRID):
        for v in np.linspace(vmin, vmax, _FIT_GRID):
            p, du, dv = gp_Pnt(), gp_Vec(), gp_Vec()
            surface.D1(float(u), float(v), p, du, dv)
            n = du.Crossed(dv)
            if n.Magnitude() > _SINGULAR:
                points.append(_xyz(p))
                normals.append(_xyz(n) / n.Magnitude())
    if len(points) < _FIT_GRID:
        return None
    fitted = fit_primitive(np.array(points), np.array(normals), fit_mm)
    if fitted is None:
        return None
    frame = gp_Ax3(gp_Pnt(*fitted.point), gp_Dir(*fitted.direction))
    if fitted.kind == PLANE:
        return PLANE, gp_Pln(frame), True
    if fitted.kind == CYLINDER:
        return CYLINDER, gp_Cylinder(frame, fitted.radius), True
    return CONE, gp_Cone(frame, fitted.semi_angle, fitted.radius), True


def _face_domain(face: TopoDS_Face, surface: Geom_Surface) -> tuple[float, float, float, float]:
    """The face's parameter box, clamped to the surface's own domain where not periodic.

    Face bounds can overshoot a B-spline's knot range by rounding (2 pi + 1 ulp), and the
    converter then refuses the face.
    """
    umin, umax, vmin, vmax = BRepTools.UVBounds_s(face)
    su0, su1, sv0, sv1 = surface.Bounds()
    if not surface.IsUPeriodic():
        umin, umax = max(umin, su0), min(umax, su1)
    if not surface.IsVPeriodic():
        vmin, vmax = max(vmin, sv0), min(vmax, sv1)
    return umin, umax, vmin, vmax


def _convert(
    surface: Geom_Surface, domain: tuple[float, float, float, float] | None, fit_mm: float
) -> Geom_Surface | None:
    """An analytic surface within ``fit_mm`` of ``surface`` (over ``domain``), or None.

    Raises:
        Exception: OCCT's own (``Standard_NullObject``...) where the converter fails.
    """
    converter = GeomConvert_SurfToAnaSurf(surface)
    if domain is None:
        analytic = converter.ConvertToAnalytical(fit_mm)
    else:
        analytic = converter.ConvertToAnalytical(fit_mm, *domain)
    if analytic is None or converter.Gap() > fit_mm:
        return None
    return analytic


def _describe(
    face_id: int, face: TopoDS_Face, kind: str, geom: Any, area: float, centre: FloatArray,
    freeform: bool,
) -> FacePrimitive:
    if kind == PLANE:
        normal = _xyz(geom.Axis().Direction())
        return FacePrimitive(face_id, kind, area, normal, centre, 0.0,
                             _outward_normal(face, normal), freeform)
    axis: gp_Ax1 = geom.Axis()
    direction = _xyz(axis.Direction())
    origin = _xyz(axis.Location())
    point = origin + np.dot(centre - origin, direction) * direction
    radius = geom.Radius() if kind == CYLINDER else geom.RefRadius()
    return FacePrimitive(face_id, kind, area, direction, point, float(radius),
                         np.zeros(3), freeform)


def _outward_normal(face: TopoDS_Face, normal: FloatArray) -> FloatArray:
    """The planar face's outward normal: ``normal`` signed by the face's own oriented normal.

    The surface normal is sampled on a 3x3 grid of the face's parameter box (a freeform plane
    can be singular at some parameters) and the face orientation is applied by BRepGProp_Face.
    """
    gprop = BRepGProp_Face(face)
    umin, umax, vmin, vmax = BRepTools.UVBounds_s(face)
    best = 0.0
    for fu in (0.5, 0.25, 0.75):
        for fv in (0.5, 0.25, 0.75):
            p, n = gp_Pnt(), gp_Vec()
            gprop.Normal(umin + fu * (umax - umin), vmin + fv * (vmax - vmin), p, n)
            mag = n.Magnitude()
            if mag > abs(best):
                best = math.copysign(mag, float(np.dot(_xyz(n), normal)))
    if best == 0.0:
        raise GeometryError("faces", "a planar face has no defined normal")
    return normal if best > 0 else -normal


def _xyz(v: Any) -> FloatArray:
    """A gp_Pnt, gp_Vec or gp_Dir as a (3,) float64 array."""
    return np.array([v.X(), v.Y(), v.Z()], dtype=np.float64)
