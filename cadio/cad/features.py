"""Geometric features of a B-rep part: mass properties, planar face groups and coaxial axes.

The ground-truth relations (parallel, perpendicular, coincident, concentric) and the face-level
mates are decided on these features, so they come from the exact B-rep. Faces are recognised as
planes, cylinders and cones by ``cadio.cad.faces`` (freeform faces included, when they fit within
``Tolerances.freeform_fit_mm``), then grouped: planes by parallel normals, cylinders and cones by
shared axis lines. Groups are built greedily in face-id order and compared with their first face,
so the result is the same after any rigid motion of the part. Everything is in the coordinates
of the shape as given.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
from OCP.Bnd import Bnd_Box
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve2d
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepTools import BRepTools
from OCP.Geom import Geom_BSplineSurface
from OCP.GeomAbs import GeomAbs_BSplineSurface, GeomAbs_Line, GeomAbs_Sphere, GeomAbs_Torus
from OCP.GeomAdaptor import GeomAdaptor_Surface
from OCP.gp import gp_Ax3
from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_VERTEX
from OCP.TopExp import TopExp_Explorer
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape

from cadio.cad.faces import (
    CYLINDER,
    PLANE,
    FacePrimitive,
    indexed_faces,
    recognise_faces,
)
from cadio.cad.solid_props import PartIntegrals, part_integrals
from cadio.cad.tessellate import MASS_PROPS_REL_EPS
from cadio.errors import GeometryError
from cadio.records import (
    AxisGroup,
    Features,
    FloatArray,
    PlaneGroup,
    canonical_direction,
    dominant_choice,
    principal_choice,
)
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances

log = logging.getLogger(__name__)

# Angles computed from dot products carry ~1e-8 rad of rounding: keep values at a tolerance in.
_ANGLE_SLACK = 1e-9
# A costly face's box is skipped (see ``tight_bbox``) when its hull reaches at most this far
# beyond the union (plus rounding relative to the coordinates): the most by which the box may
# fall short of the exact geometry. OpenCascade itself enlarges an optimised face box by
# Precision::Confusion (1e-7 mm), and its optimisation falls short by up to 4.2e-5 mm.
_HULL_MARGIN_MM = 1e-6
_HULL_MARGIN_REL = 1e-9
# ...and the face's parameter box is widened by this fraction (plus 1e-8) before bounding it:
# OpenCascade's optimal box works on its own, slightly different, parameter bounds.
_UV_WIDEN = 1e-6
# An edge's ends lie on a side of the face's parameter box within this share of its range.
_SIDE_REL = 1e-9


def extract_features(
    shape: TopoDS_Shape,
    tol: Tolerances = DEFAULT_TOLERANCES,
    integrals: PartIntegrals | None = None,
) -> Features:
    """Compute the geometric features of one part from its exact B-rep.

    Args:
        shape: a solid (or compound of solids), mm.
        tol: ``group_angle_deg`` groups planes, ``coaxial_deg``/``coaxial_mm`` group axes,
            ``freeform_fit_mm`` bounds the fit of freeform faces and ``dominant_group_deg``,
            ``dominant_area_ratio`` pick the dominant plane direction.
        integrals: ``part_integrals(shape, indexed_faces(shape), MASS_PROPS_REL_EPS)`` when
            the caller has them already (they are the costliest part).

    Returns:
        Features: volume centroid and volume, total area, tight axis-aligned box, plane groups
        and cylinder/cone axis groups (ordered by their first face id, except that the
        principal axis comes first), principal plane normal and principal cylinder axis with
        tie flags, the dominant plane direction, face counts.

    Raises:
        GeometryError: when the shape has no face or no volume.
    """
    faces = indexed_faces(shape)
    if not faces:
        raise GeometryError("features", "shape has no faces")
    if integrals is None:
        integrals = part_integrals(shape, faces, MASS_PROPS_REL_EPS)
    volume, centroid = integrals.volume, integrals.centroid
    if volume == 0.0:
        raise GeometryError("features", "shape encloses no volume")
    props = list(integrals.face_props)
    prims = recognise_faces(faces, tol, props)
    planes = group_planes([p for p in prims if p.kind == PLANE], tol.group_angle_deg)
    axes = group_axes([p for p in prims if p.kind != PLANE], tol.coaxial_deg, tol.coaxial_mm)
    plane_pick, plane_tie = principal_choice([g.area for g in planes])
    cylinders = [a for a in axes if a.kind == CYLINDER]
    axis_pick, axis_tie = principal_choice([a.area for a in cylinders])
    if axis_pick is not None:
        axes = _principal_first(axes, cylinders[axis_pick])
    dominant, runner_up = dominant_choice(planes, tol.dominant_group_deg,
                                          tol.dominant_area_ratio)
    bbox_min, bbox_max = tight_bbox(shape)
    log.debug("%d faces: %d planes/cylinders/cones, %d of them fitted to freeform surfaces",
              len(faces), len(prims), sum(p.freeform for p in prims))
    return Features(
        centroid=centroid, bbox_min=bbox_min, bbox_max=bbox_max, volume=volume,
        area=float(sum(a for a, _ in props)), planes=planes, axes=axes,
        principal_plane=None if plane_pick is None else planes[plane_pick].normal,
        principal_axis=None if axis_pick is None else cylinders[axis_pick],
        principal_plane_tie=plane_tie, principal_axis_tie=axis_tie,
        n_faces=len(faces), n_freeform_recognised=sum(p.freeform for p in prims),
        dominant_plane=dominant, dominant_runner_up=runner_up,
    )


def tight_bbox(shape: TopoDS_Shape) -> tuple[FloatArray, FloatArray]:
    """Axis-aligned box of the exact geometry (not the mesh, not enlarged by tolerances).

    The union of the faces' boxes: OpenCascade's optimal box of each face
    (``BRepBndLib.AddOptimal_s`` without triangulation or tolerances, which OpenCascade
    enlarges by 1e-7 mm), except where a cheaper one is as good. A B-spline, torus or sphere
    face costs OpenCascade an optimisation (up to ~50 ms on the real files):

    * a torus or sphere face that is its whole parameter box is boxed in closed form, exactly
      (OpenCascade's optimisation falls short of two real fillets by up to 4.2e-5 mm);
    * any other such face is skipped when a cheap box that surely holds it (see
      ``_hull_box``) lies within ``_HULL_MARGIN_MM`` (plus rounding) of the union of the faces
      done so far.

    So the result holds the exact geometry, and exceeds it by at most ~1e-6 mm.

    Args:
        shape: any non-empty shape, mm.

    Returns:
        (bbox_min, bbox_max), each (3,) float64 mm.

    Raises:
        GeometryError: when the shape has no geometry to bound.
    """
    if _has_loose_edges(shape):
        lo, hi = _optimal_box(shape)
    else:
        lo, hi = _union_of_faces(indexed_faces(shape))
    if not np.all(lo <= hi):
        raise GeometryError("features", "shape has an empty bounding box")
    return lo, hi


def _union_of_faces(faces: Sequence[TopoDS_Face]) -> tuple[FloatArray, FloatArray]:
    """Union of the faces' boxes; costly faces last, skipped where they cannot count."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    costly = []
    for face in faces:
        hull = _hull_box(face)
        if hull is None:
            lo, hi = _union(lo, hi, _optimal_box(face))
        elif hull[2]:
            lo, hi = _union(lo, hi, hull[:2])
        else:
            costly.append((face, hull))
    for face, (hull_lo, hull_hi, _) in costly:
        margin = _HULL_MARGIN_MM + _HULL_MARGIN_REL * float(np.max(np.abs([hull_lo, hull_hi])))
        if np.all(hull_lo + margin >= lo) and np.all(hull_hi - margin <= hi):
            continue
        lo, hi = _union(lo, hi, _optimal_box(face))
    return lo, hi


def _union(
    lo: FloatArray, hi: FloatArray, box: tuple[FloatArray, FloatArray]
) -> tuple[FloatArray, FloatArray]:
    return np.minimum(lo, box[0]), np.maximum(hi, box[1])


def _optimal_box(shape: TopoDS_Shape) -> tuple[FloatArray, FloatArray]:
    """OpenCascade's optimal box of a shape; an empty one is (+inf, -inf)."""
    box = Bnd_Box()
    BRepBndLib.AddOptimal_s(shape, box, False, False)
    if box.IsVoid():
        return np.full(3, np.inf), np.full(3, -np.inf)
    x0, y0, z0, x1, y1, z1 = box.Get()
    return np.array([x0, y0, z0]), np.array([x1, y1, z1])


def _hull_box(face: TopoDS_Face) -> tuple[FloatArray, FloatArray, bool] | None:
    """(lo, hi, exact): a box surely holding a costly face, and whether it is the face's own
    box; or None for a face OpenCascade boxes cheaply.

    The bounds work on the face's parameter box, widened a little (``_uv_box``), except an
    exact one. B-spline: the box of the poles of the surface cut down to it. Torus and
    sphere: the box of the surface over it (``_revolved_hull``), exact when the face is its
    whole parameter box. Planes, cylinders and cones are boxed from their edges by
    OpenCascade; other freeform kinds are rare and simply computed.
    """
    surface = GeomAdaptor_Surface(BRep_Tool.Surface_s(face))  # located: shape coordinates
    kind = surface.GetType()
    if kind == GeomAbs_BSplineSurface:
        return (*_bspline_hull(surface.BSpline(), _uv_box(face)), False)
    if kind in (GeomAbs_Torus, GeomAbs_Sphere):
        if kind == GeomAbs_Torus:
            torus = surface.Torus()
            position, major, minor = torus.Position(), torus.MajorRadius(), torus.MinorRadius()
        else:
            sphere = surface.Sphere()  # a torus of major radius 0 in OpenCascade's formulas
            position, major, minor = sphere.Position(), 0.0, sphere.Radius()
        uv = BRepTools.UVBounds_s(face)
        if _fills_uv_box(face, uv) and major + minor * _cos_range(uv[2], uv[3])[0] >= 0.0:
            return (*_revolved_hull(position, major, minor, uv), True)
        return (*_revolved_hull(position, major, minor, _uv_box(face)), False)
    return None


def _fills_uv_box(face: TopoDS_Face, uv: tuple[float, float, float, float]) -> bool:
    """Whether the face is its whole parameter box: every edge on the face is a line along
    one of the box's four sides (its seams and poles included)."""
    u0, u1, v0, v1 = uv
    du, dv = _SIDE_REL * max(u1 - u0, 1.0), _SIDE_REL * max(v1 - v0, 1.0)
    explorer = TopExp_Explorer(face, TopAbs_EDGE)
    while explorer.More():
        curve = BRepAdaptor_Curve2d(TopoDS.Edge_s(explorer.Current()), face)
        explorer.Next()
        if curve.GetType() != GeomAbs_Line:
            return False
        a, b = curve.Value(curve.FirstParameter()), curve.Value(curve.LastParameter())
        on_side = any(abs(a.X() - u) <= du and abs(b.X() - u) <= du for u in (u0, u1)) or \
            any(abs(a.Y() - v) <= dv and abs(b.Y() - v) <= dv for v in (v0, v1))
        if not on_side:
            return False
    return True


def _uv_box(face: TopoDS_Face) -> tuple[float, float, float, float]:
    """The face's parameter box, widened beyond the rounding of OpenCascade's own UV bounds."""
    u0, u1, v0, v1 = BRepTools.UVBounds_s(face)
    du, dv = _UV_WIDEN * (u1 - u0) + 1e-8, _UV_WIDEN * (v1 - v0) + 1e-8
    return u0 - du, u1 + du, v0 - dv, v1 + dv


def _bspline_hull(
    surface: Geom_BSplineSurface, uv: tuple[float, float, float, float]
) -> tuple[FloatArray, FloatArray]:
    """Box of the poles of ``surface`` cut down to ``uv`` (knots inserted at its ends), which
    hold it there (a rational B-spline with positive weights lies in the convex hull of its
    poles); the box of the poles that reach into ``uv`` where the cut fails."""
    u_lo, u_hi, v_lo, v_hi = surface.Bounds()
    cut = surface.Copy()
    try:
        cut.Segment(max(uv[0], u_lo) if not surface.IsUPeriodic() else uv[0],
                    min(uv[1], u_hi) if not surface.IsUPeriodic() else uv[1],
                    max(uv[2], v_lo) if not surface.IsVPeriodic() else uv[2],
                    min(uv[3], v_hi) if not surface.IsVPeriodic() else uv[3])
    except Exception:  # OCP's Standard_* exceptions share no Python base class but Exception
        return _reaching_hull(surface, uv)
    xyz = _poles(cut).reshape(-1, 3)
    return xyz.min(axis=0), xyz.max(axis=0)


def _poles(surface: Geom_BSplineSurface) -> FloatArray:
    """The surface's poles, (u poles, v poles, 3)."""
    poles = surface.Poles()
    return np.array([[poles.Value(i, j).Coord()
                      for j in range(poles.LowerCol(), poles.UpperCol() + 1)]
                     for i in range(poles.LowerRow(), poles.UpperRow() + 1)])


def _reaching_hull(
    surface: Geom_BSplineSurface, uv: tuple[float, float, float, float]
) -> tuple[FloatArray, FloatArray]:
    """Box of the poles that shape ``surface`` over ``uv`` (all of them along periodic sides)."""
    xyz = _poles(surface)
    rows = _reaching(surface.UKnotSequence(), surface.UDegree(), len(xyz), uv[0], uv[1],
                     surface.IsUPeriodic())
    cols = _reaching(surface.VKnotSequence(), surface.VDegree(), xyz.shape[1], uv[2], uv[3],
                     surface.IsVPeriodic())
    used = xyz[rows][:, cols].reshape(-1, 3)
    return used.min(axis=0), used.max(axis=0)


def _reaching(
    flat_knots: Any, degree: int, n: int, lo: float, hi: float, periodic: bool
) -> npt.NDArray[np.bool_]:
    """Which of ``n`` B-spline basis functions are non-zero somewhere on [lo, hi]."""
    if periodic:
        return np.ones(n, dtype=bool)
    t = np.array([flat_knots.Value(k) for k in range(flat_knots.Lower(), flat_knots.Upper() + 1)])
    return np.asarray((t[:n] <= hi) & (t[degree + 1:degree + 1 + n] >= lo))


def _revolved_hull(
    position: gp_Ax3, major: float, minor: float, uv: tuple[float, float, float, float]
) -> tuple[FloatArray, FloatArray]:
    """Box of P(u, v) = C + (major + minor cos v)(cos u X + sin u Y) + minor sin v Z over uv.

    Per coordinate k, cos u X_k + sin u Y_k = A cos(u - phi) ranges over [m, M] on [u0, u1].
    Where rho = major + minor cos v >= 0 the extremes over u at each v are rho M and rho m,
    so the largest P_k is C_k + major M + minor max(M cos v + Z_k sin v), one more cosine
    range over [v0, v1], and the smallest likewise with m: the box of the whole patch, exact
    to rounding. Elsewhere (a spindle torus) the product of the ranges bounds it.
    """
    u0, u1, v0, v1 = uv
    x, y, z = (np.array(d.Coord()) for d in
               (position.XDirection(), position.YDirection(), position.Direction()))
    centre = np.array(position.Location().Coord())
    rho = major + minor * np.array(_cos_range(v0, v1))  # (lo, hi)
    sin_v = np.array(_cos_range(v0 - math.pi / 2, v1 - math.pi / 2))
    lo, hi = np.empty(3), np.empty(3)
    for k in range(3):
        # cos u x_k + sin u y_k = A cos(u - phi): its exact range over [u0, u1]
        amp, phi = math.hypot(x[k], y[k]), math.atan2(y[k], x[k])
        radial = amp * np.array(_cos_range(u0 - phi, u1 - phi))
        if rho[0] >= 0.0:
            # r cos v + z_k sin v = B cos(v - psi)
            low, high = (major * r + minor * math.hypot(r, z[k])
                         * np.array(_cos_range(v0 - math.atan2(z[k], r), v1 - math.atan2(z[k], r)))
                         for r in radial)
            lo[k], hi[k] = centre[k] + low[0], centre[k] + high[1]
        else:
            products = np.outer(rho, radial)
            axial = minor * z[k] * sin_v
            lo[k] = centre[k] + products.min() + axial.min()
            hi[k] = centre[k] + products.max() + axial.max()
    return lo, hi


def _cos_range(lo: float, hi: float) -> tuple[float, float]:
    """(min, max) of cos over [lo, hi] radians."""
    if hi - lo >= 2 * math.pi:
        return -1.0, 1.0
    ends = (math.cos(lo), math.cos(hi))
    top = 1.0 if 2 * math.pi * math.floor(hi / (2 * math.pi)) >= lo else max(ends)
    bottom = -1.0 if 2 * math.pi * math.floor((hi - math.pi) / (2 * math.pi)) + math.pi >= lo \
        else min(ends)
    return bottom, top


def _has_loose_edges(shape: TopoDS_Shape) -> bool:
    """Whether the shape has edges outside faces or vertices outside edges (not a solid's)."""
    return bool(TopExp_Explorer(shape, TopAbs_EDGE, TopAbs_FACE).More()
                or TopExp_Explorer(shape, TopAbs_VERTEX, TopAbs_EDGE).More())


def _parallel(a: FloatArray, b: FloatArray, angle_deg: float) -> bool:
    """Directions a, b (unit) within ``angle_deg`` of each other, sign ignored."""
    return abs(float(np.dot(a, b))) >= math.cos(math.radians(angle_deg)) - _ANGLE_SLACK


def _cluster(
    prims: Sequence[FacePrimitive], same: Callable[[FacePrimitive, FacePrimitive], bool]
) -> list[list[FacePrimitive]]:
    """Greedy clustering in face-id order: a face joins the first cluster whose seed matches."""
    clusters: list[list[FacePrimitive]] = []
    for p in prims:
        for c in clusters:
            if same(c[0], p):
                c.append(p)
                break
        else:
            clusters.append([p])
    return clusters


def _mean_direction(members: Sequence[FacePrimitive]) -> FloatArray:
    """Area-weighted mean of the members' directions, signs aligned to the first, canonical."""
    seed = members[0].direction
    total = np.zeros(3)
    for m in members:
        total += m.area * (1.0 if np.dot(m.direction, seed) >= 0 else -1.0) * m.direction
    return canonical_direction(total)


def group_planes(planes: Sequence[FacePrimitive], angle_deg: float) -> tuple[PlaneGroup, ...]:
    """Group planar faces whose normals are parallel within ``angle_deg`` (sign ignored).

    Args:
        planes: planar faces in id order.
        angle_deg: largest angle between a face's normal and its group's first face's normal.

    Returns:
        Plane groups in order of their first face id, with a canonical area-weighted normal.
    """
    clusters = _cluster(planes, lambda a, b: _parallel(a.direction, b.direction, angle_deg))
    groups = []
    for members in clusters:
        normal = _mean_direction(members)
        groups.append(PlaneGroup(
            normal=normal,
            area=float(sum(m.area for m in members)),
            face_ids=tuple(m.face_id for m in members),
            face_areas=tuple(m.area for m in members),
            offsets=tuple(float(np.dot(normal, m.point)) for m in members),
            outward=tuple(1 if np.dot(m.outward, normal) > 0 else -1 for m in members),
        ))
    return tuple(groups)


def _line_distance(a: FacePrimitive, b: FacePrimitive) -> float:
    """Largest distance of either axis point from the other axis line, mm."""
    def off(p: FloatArray, q: FloatArray, d: FloatArray) -> float:
        r = p - q
        return float(np.linalg.norm(r - np.dot(r, d) * d))

    return max(off(a.point, b.point, b.direction), off(b.point, a.point, a.direction))


def group_axes(
    prims: Sequence[FacePrimitive], angle_deg: float, distance_mm: float
) -> tuple[AxisGroup, ...]:
    """Group cylindrical (and, separately, conical) faces sharing one axis line.

    Args:
        prims: cylinder and cone faces in id order.
        angle_deg: largest angle between two axes of one group.
        distance_mm: largest distance between two axis lines of one group.

    Returns:
        Axis groups in order of their first face id; each has one kind, a canonical direction
        and the point of its axis line closest to the origin.
    """
    def same(a: FacePrimitive, b: FacePrimitive) -> bool:
        return (a.kind == b.kind and _parallel(a.direction, b.direction, angle_deg)
                and _line_distance(a, b) <= distance_mm)

    groups = []
    for members in _cluster(prims, same):
        direction = _mean_direction(members)
        total = float(sum(m.area for m in members))
        point = sum(m.area * m.point for m in members) / total if total > 0 else members[0].point
        point = point - np.dot(point, direction) * direction
        groups.append(AxisGroup(
            kind=members[0].kind, direction=direction, point=np.asarray(point, dtype=np.float64),
            area=total, face_ids=tuple(m.face_id for m in members),
            radii=tuple(m.radius for m in members),
        ))
    return tuple(groups)


def _principal_first(axes: tuple[AxisGroup, ...], principal: AxisGroup) -> tuple[AxisGroup, ...]:
    """Move the principal axis group to the front, keeping the others in face-id order.

    ``Features.to_dict`` and ``Features.transformed`` locate it with ``tuple.index``, which
    compares earlier groups by value, and comparing numpy fields raises; at the front it is
    found by identity first.
    """
    return (principal, *(a for a in axes if a is not principal))


