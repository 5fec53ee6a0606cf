"""What the face mates need of a part: planar faces and axis lines, moved without recomputing.

``describe_shape`` (``describe_part`` for a solid of an assembly) gives a part's planar faces
(outward normals, centroids, reach) and the axis lines of its cylinder and cone faces, in the
frame of the shape; ``PartGeometry.placed`` moves them rigidly (the faces are only relocated),
so a part described once can be placed in many scenes. ``face_overlap`` is the area two opposed,
nearly coplanar faces have in common. Pruning and exact distances live in
``cadio.truth.proximity``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from OCP.Bnd import Bnd_Box
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve
from OCP.BRepAlgoAPI import BRepAlgoAPI_Common
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepGProp import BRepGProp, BRepGProp_Face
from OCP.BRepTools import BRepTools
from OCP.gp import gp_Ax1, gp_Dir, gp_Pnt, gp_Trsf, gp_Vec
from OCP.GProp import GProp_GProps
from OCP.TopAbs import TopAbs_EDGE
from OCP.TopExp import TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape
from OCP.TopTools import TopTools_ListOfShape

from cadio.cad.faces import CONE, indexed_faces
from cadio.cad.features import extract_features
from cadio.cad.step import StepSolid
from cadio.records import AxisGroup, Features, FloatArray, apply_pose
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances

log = logging.getLogger(__name__)

_SAMPLES_PER_EDGE = 9
SLACK = 1e-9  # values computed exactly at a tolerance stay inside despite rounding


# ---------------------------------------------------------------- per-part geometry


@dataclass(frozen=True)
class AxisFace:
    """A cylindrical or conical face on an axis line.

    kind: "cylinder" or "cone". convex: a shaft or boss, not a hole. ends (2, 3) mm: its axis
    points at the lowest and highest axial end; radii (2,) mm: its radius there (equal for a
    cylinder; a cone's from a line fitted to its exact boundary points).
    """

    face_id: int
    kind: str
    convex: bool
    ends: FloatArray
    radii: FloatArray

    @property
    def radius(self) -> float:
        """Mean radius, mm."""
        return float(self.radii.mean())

    def radius_at(self, point: FloatArray) -> float:
        """Radius at the axial station of ``point`` (near the axis), mm: linear in the station,
        so a cone's beyond its ends too."""
        span = self.ends[1] - self.ends[0]
        length2 = float(span @ span)
        if length2 == 0.0:
            return self.radius
        s = float((point - self.ends[0]) @ span) / length2
        return float(self.radii[0] + s * (self.radii[1] - self.radii[0]))

    def semi_angle_deg(self, direction: FloatArray) -> float:
        """Signed semi-angle, degrees: positive when the radius grows along ``direction``."""
        run = float((self.ends[1] - self.ends[0]) @ direction)
        rise = float(self.radii[1] - self.radii[0])
        return 0.0 if run == 0.0 else math.degrees(math.atan(rise / run))

    def moved(self, pose: FloatArray) -> AxisFace:
        """This face after the rigid motion ``pose`` (4, 4), mm."""
        return replace(self, ends=apply_pose(pose, self.ends))


@dataclass(frozen=True)
class AxisLine:
    """Coaxial faces of one part: unit direction, mid point and ends (2, 3) of their extent, mm."""

    direction: FloatArray
    mid: FloatArray
    ends: FloatArray
    faces: tuple[AxisFace, ...]

    def moved(self, pose: FloatArray) -> AxisLine:
        """This line and its faces after the rigid motion ``pose`` (4, 4), mm."""
        return AxisLine(pose[:3, :3] @ self.direction, apply_pose(pose, self.mid),
                        apply_pose(pose, self.ends), tuple(f.moved(pose) for f in self.faces))


@dataclass(frozen=True, eq=False)
class PartGeometry:
    """A part and what the mates need: planar faces (ids, outward normals (k, 3), area centroids
    (k, 3) mm, reach (k,) mm = largest distance from centroid to boundary), axis lines and the
    solid's axis-aligned box (6,) (lo, hi, mm, enlarged by its tolerance), all in one frame."""

    index: int
    part_id: str
    name: str
    path: str
    shape: TopoDS_Shape
    features: Features
    faces: list[TopoDS_Face]
    plane_ids: list[int]
    normals: FloatArray
    centres: FloatArray
    reach: FloatArray
    lines: tuple[AxisLine, ...]
    box: FloatArray

    def placed(self, pose: FloatArray, index: int | None = None) -> PartGeometry:
        """This part after the rigid motion ``pose`` (4, 4) float64 (mm), as part ``index``
        of a set: the shape and faces relocated (their geometry is shared, not copied), the
        vectors turned, the box that of the moved box's corners (it still holds the part)."""
        at = self.index if index is None else index
        if np.array_equal(pose, np.eye(4)):
            return self if at == self.index else replace(self, index=at)
        loc = TopLoc_Location(pose_trsf(pose))
        corners = np.array([[x, y, z] for x in self.box[0::3] for y in self.box[1::3]
                            for z in self.box[2::3]])
        moved = apply_pose(pose, corners)
        return replace(
            self, index=at, shape=self.shape.Moved(loc),
            features=self.features.transformed(pose),
            faces=[TopoDS.Face_s(f.Moved(loc)) for f in self.faces],
            normals=self.normals @ pose[:3, :3].T, centres=apply_pose(pose, self.centres),
            lines=tuple(line.moved(pose) for line in self.lines),
            box=np.concatenate([moved.min(axis=0), moved.max(axis=0)]))


def pose_trsf(pose: FloatArray) -> gp_Trsf:
    """OpenCascade's transformation of a rigid (4, 4) pose, mm."""
    trsf = gp_Trsf()
    p = np.asarray(pose, dtype=np.float64)
    trsf.SetValues(*p[0], *p[1], *p[2])
    return trsf


def describe_part(solid: StepSolid, index: int, part_id: str, tol: Tolerances) -> PartGeometry:
    """Features, planar faces and axis lines of one solid (assembly frame)."""
    return describe_shape(solid.shape, part_id, tol, index=index, name=solid.info.name,
                          path=solid.info.path_in_assembly)


def describe_shape(shape: TopoDS_Shape, part_id: str, tol: Tolerances = DEFAULT_TOLERANCES,
                   features: Features | None = None, *, index: int = 0, name: str = "",
                   path: str = "") -> PartGeometry:
    """What the face mates need of a solid, in the shape's frame.

    Args:
        shape: the solid, mm.
        part_id, index, name, path: how the rows name it.
        tol: tolerances for the features (when not given) and the axis lines.
        features: its features (``extract_features(shape, tol)``) where already known, e.g.
            read back from the workspace: the costliest part.
    """
    faces = indexed_faces(shape)
    features = extract_features(shape, tol) if features is None else features
    ids, normals, centres, reach = [], [], [], []
    for g in features.planes:
        for fid, offset, outward in zip(g.face_ids, g.offsets, g.outward, strict=True):
            pts = _boundary(faces[fid])
            centre = pts.mean(axis=0) if len(pts) else g.normal * offset
            centre = centre - (float(np.dot(g.normal, centre)) - offset) * g.normal
            ids.append(fid)
            normals.append(outward * g.normal)
            centres.append(centre)
            reach.append(float(np.max(np.linalg.norm(pts - centre, axis=1))) if len(pts) else 0.0)
    box = Bnd_Box()
    BRepBndLib.Add_s(shape, box, False)  # from the geometry, enlarged by its tolerance
    return PartGeometry(
        index=index, part_id=part_id, name=name, path=path,
        shape=shape, features=features, faces=faces, plane_ids=ids,
        normals=np.array(normals).reshape(-1, 3), centres=np.array(centres).reshape(-1, 3),
        reach=np.array(reach, dtype=np.float64), lines=_axis_lines(features.axes, faces, tol),
        box=np.array(box.Get(), dtype=np.float64),
    )


def _boundary(face: TopoDS_Face) -> FloatArray:
    """Points sampled along the face's edges (m, 3), mm (degenerate edges skipped)."""
    points = []
    explorer = TopExp_Explorer(face, TopAbs_EDGE)
    while explorer.More():
        edge = TopoDS.Edge_s(explorer.Current())
        explorer.Next()
        if BRep_Tool.Degenerated_s(edge):
            continue
        curve = BRepAdaptor_Curve(edge)
        for u in np.linspace(curve.FirstParameter(), curve.LastParameter(), _SAMPLES_PER_EDGE):
            p = curve.Value(float(u))
            points.append((p.X(), p.Y(), p.Z()))
    return np.array(points, dtype=np.float64).reshape(-1, 3)


def _axis_face(face_id: int, face: TopoDS_Face, kind: str, radius: float, d: FloatArray,
               point: FloatArray) -> AxisFace:
    """One face on the axis line (d unit, point): its axial ends, radii there and convexity."""
    pts = _boundary(face)
    rel = pts - point
    t = rel @ d
    span = np.array([t.min(), t.max()] if len(t) else [0.0, 0.0])
    radii = np.full(2, float(radius))
    if kind == CONE and len(pts) and np.ptp(t) > 0.0:  # the reference radius may be anywhere
        rho = np.linalg.norm(rel - np.outer(t, d), axis=1)
        radii = np.polyval(np.polyfit(t, rho, 1), span)
    return AxisFace(face_id, kind, _is_convex(face, point, d), point + np.outer(span, d), radii)


def _is_convex(face: TopoDS_Face, point: FloatArray, d: FloatArray) -> bool:
    """True when the face's outward normal points away from its axis (a shaft, not a hole)."""
    gprop = BRepGProp_Face(face)
    umin, umax, vmin, vmax = BRepTools.UVBounds_s(face)
    best = 0.0
    for fu, fv in ((0.5, 0.5), (0.25, 0.25), (0.75, 0.75), (0.25, 0.75), (0.75, 0.25)):
        p, n = gp_Pnt(), gp_Vec()
        gprop.Normal(umin + fu * (umax - umin), vmin + fv * (vmax - vmin), p, n)
        rel = np.array([p.X(), p.Y(), p.Z()]) - point
        radial = rel - np.dot(rel, d) * d
        value = float(np.dot(radial, [n.X(), n.Y(), n.Z()]))
        if abs(value) > abs(best):
            best = value
    return best > 0.0


def _axis_lines(groups: Sequence[AxisGroup], faces: list[TopoDS_Face],
                tol: Tolerances) -> tuple[AxisLine, ...]:
    """Merge the part's cylinder and cone axis groups that share a line (greedy, in order)."""
    clusters: list[list[AxisGroup]] = []
    for g in groups:
        for c in clusters:
            if _coaxial(c[0].direction, c[0].point, g.direction, g.point, tol):
                c.append(g)
                break
        else:
            clusters.append([g])
    lines = []
    for members in clusters:
        d, base = members[0].direction, members[0].point
        axis_faces = tuple(
            _axis_face(fid, faces[fid], g.kind, r, d, base)
            for g in members for fid, r in zip(g.face_ids, g.radii, strict=True))
        t = np.concatenate([f.ends @ d for f in axis_faces])
        ends = base + np.outer([t.min(), t.max()], d)
        lines.append(AxisLine(d, ends.mean(axis=0), ends, axis_faces))
    return tuple(lines)


def _coaxial(da: FloatArray, pa: FloatArray, db: FloatArray, pb: FloatArray,
             tol: Tolerances) -> bool:
    angle = math.degrees(math.atan2(np.linalg.norm(np.cross(da, db)), abs(np.dot(da, db))))
    gap = _line_gap(pa, da, pb, db)
    return angle <= tol.coaxial_deg + SLACK and gap <= tol.coaxial_mm + SLACK


def _line_gap(pa: FloatArray, da: FloatArray, pb: FloatArray, db: FloatArray) -> float:
    """Largest distance of either point from the other's axis line (unit directions), mm."""
    def off(p: FloatArray, q: FloatArray, d: FloatArray) -> float:
        r = p - q
        return float(np.linalg.norm(r - np.dot(r, d) * d))

    return max(off(pa, pb, db), off(pb, pa, da))



def face_overlap(fa: TopoDS_Face, fb: TopoDS_Face, na: FloatArray, ca: FloatArray,
                 nb: FloatArray, cb: FloatArray,
                 fuzzy_mm: float = DEFAULT_TOLERANCES.overlap_fuzzy_mm) -> tuple[float, FloatArray]:
    """(area mm^2, centroid (3,) mm) of the overlap of two nearly coplanar, opposed faces.

    Face b is turned about its centroid until its normal is exactly -na and shifted onto a's
    plane (a motion of at most ``mate_angle_deg`` and ``contact_mm``), then intersected with a
    by a Boolean common whose fuzzy value ``fuzzy_mm`` (``Tolerances.overlap_fuzzy_mm``) makes
    the two one plane: ``na`` is a's plane group normal, off a's own by rounding, and over a
    large face that alone leaves an exact Boolean with nothing in common.
    """
    axis = np.cross(nb, -na)
    sin = float(np.linalg.norm(axis))
    turn = gp_Trsf()
    if sin > 1e-12:
        turn.SetRotation(gp_Ax1(gp_Pnt(*cb), gp_Dir(*(axis / sin))),
                         math.atan2(sin, float(np.dot(nb, -na))))
    shift = gp_Trsf()
    shift.SetTranslation(gp_Vec(*(-float(np.dot(cb - ca, na)) * na)))
    moved = fb.Moved(TopLoc_Location(shift.Multiplied(turn)))
    common = _fuzzy_common(fa, moved, fuzzy_mm)
    if not common.IsDone():
        log.warning("Boolean common of two planar faces failed: no overlap assumed")
        return 0.0, ca
    props = GProp_GProps()
    BRepGProp.SurfaceProperties_s(common.Shape(), props)
    c = props.CentreOfMass()
    return float(props.Mass()), np.array([c.X(), c.Y(), c.Z()])


def _fuzzy_common(a: TopoDS_Shape, b: TopoDS_Shape, fuzzy_mm: float) -> BRepAlgoAPI_Common:
    """The Boolean common of a and b, sub-shapes within ``fuzzy_mm`` taken as coincident.

    Non-destructive: by default a Boolean may raise the tolerances of its arguments' edges and
    vertices in place, which would change the parts for every later distance and Boolean.
    """
    arguments, tools = TopTools_ListOfShape(), TopTools_ListOfShape()
    arguments.Append(a)
    tools.Append(b)
    common = BRepAlgoAPI_Common()
    common.SetArguments(arguments)
    common.SetTools(tools)
    common.SetFuzzyValue(fuzzy_mm)
    common.SetNonDestructive(True)
    common.Build()
    return common
