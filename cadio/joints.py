"""Which parts touch, and the joint a CAD user would set between two parts from their mates.

Contact (``contact_proxy``, ``in_contact``): is the exact B-rep distance between two solids at
most a tolerance? Exact face-to-face distances (BRepExtrema) are costly on freeform faces and
large housings (tens of seconds for one pair of the PM4 pump), so a cheap certificate rules
pairs out first: a coarse mesh of a copy of each part (chordal deflection ``MESH_DEFLECTION_MM``)
is sampled every ``SAMPLE_SPACING_MM`` and the samples' nearest distance, less the sampling and
mesh slack, is a lower bound on the true distance. Face pairs it cannot rule out are measured
exactly, the likeliest first, stopping at the first hit; the answer is the exact test's, so it
does not change when the assembly moves.

Joints: each face mate is read as a bilateral kinematic constraint, as CAD mates are (a
coincident mate keeps two faces together in both directions, so a part resting on a plate is
"planar", not "free upwards"). The relative motion of part b with respect to part a is a twist
(w, v): angular velocity w and the velocity v of a reference point c. A constraint allows only the
twists that keep it satisfied:

- coincident planes, outward normal n, contact point p: w parallel to n (no tilting) and no
  velocity of p along n (no lift-off): 3 linear equations;
- a fit, a shaft in a bore (concentric faces, one convex inside one concave, radial clearance at
  most ``MateConfig.fit_clearance_mm``) on the axis line (d, p): w parallel to d and the
  velocity of p parallel to d: 4 equations. Two coaxial holes ("aligned") or a shaft far inside a
  bore ("nested") constrain nothing and are not used.

The allowed twists are the null space of the stacked equations (SVD). Its dimension is the number
of degrees of freedom and its shape names the joint:

======  ==========================================================  ============
 dof     allowed motion                                              kinematic
======  ==========================================================  ============
 0       none                                                        fastened
 1       a rotation about a line, without pitch                      revolute
 1       a translation                                               slider
 2       rotation about and translation along one line               cylindrical
 3       rotation about a normal n, translations perpendicular to n  planar
======  ==========================================================  ============

Anything else (a helical twist, two translations without rotation) is "other" and has no CAD
name. Singular values below sin(``Tolerances.parallel_deg``) count as zero: two contacts whose
normals differ by less than a degree constrain the same directions.

Why a bolt is "revolute": a bolt whose head sits on a plate and whose shank fits the hole can
still turn about its axis; the thread that stops it is not in the B-rep (STEP stores the shank as
a smooth cylinder), so "fastened" cannot be derived from geometry. Both answers are kept: the
``kinematic`` joint is pure geometry; the ``suggested`` joint is what a CAD user would set. It
equals the kinematic one except for one documented rule: when either part's name says it is a
fastener (bolt, screw, nut, washer, rivet, stud), the suggestion is ``fastened``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from OCP.Bnd import Bnd_Box
from OCP.BRep import BRep_Tool
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepBuilderAPI import BRepBuilderAPI_Copy
from OCP.BRepClass3d import BRepClass3d_SolidClassifier
from OCP.BRepExtrema import BRepExtrema_DistShapeShape
from OCP.BRepMesh import BRepMesh_IncrementalMesh
from OCP.TopAbs import TopAbs_IN, TopAbs_VERTEX
from OCP.TopExp import TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape
from scipy.spatial import cKDTree

from cadio.faces import indexed_faces
from cadio.records import FloatArray, canonical_direction
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances

PLANE, AXIS = "plane", "axis"
FASTENED, REVOLUTE, SLIDER, CYLINDRICAL, PLANAR, OTHER = (
    "fastened", "revolute", "slider", "cylindrical", "planar", "other")

# Joint names per CAD system: Onshape mates, FreeCAD Assembly joints, Fusion 360 joints.
CAD_NAMES: dict[str, dict[str, str]] = {
    FASTENED: {"onshape": "Fastened", "freecad": "Fixed", "fusion360": "Rigid"},
    REVOLUTE: {"onshape": "Revolute", "freecad": "Revolute", "fusion360": "Revolute"},
    SLIDER: {"onshape": "Slider", "freecad": "Slider", "fusion360": "Slider"},
    CYLINDRICAL: {"onshape": "Cylindrical", "freecad": "Cylindrical", "fusion360": "Cylindrical"},
    PLANAR: {"onshape": "Planar", "freecad": "Planar", "fusion360": "Planar"},
}
# Contact certificate: a coarse mesh (chordal deflection mm, or the part's size / MESH_RELATIVE
# if larger) cut into triangles no longer than the spacing (mm, or size / SAMPLE_RELATIVE); their
# centroids are the samples: every point of such a triangle is within 2/3 spacing of one.
# BRepMesh keeps the deviation near the deflection, not strictly under it: MESH_SAFETY doubles it.
MESH_DEFLECTION_MM, MESH_RELATIVE, MESH_SAFETY = 0.2, 1000.0, 2.0
SAMPLE_SPACING_MM, SAMPLE_RELATIVE = 1.5, 100.0
# Names of parts that CAD users fasten whatever the geometry allows (threads are not modelled).
FASTENER_NAME = re.compile(r"bolt|screw|nut|washer|rivet|stud", re.IGNORECASE)


@dataclass(frozen=True)
class Constraint:
    """One face mate as a kinematic constraint, in the assembly frame.

    kind: "plane" (coincident planar contact) or "axis" (shaft fitted in a bore).
    direction: (3,) unit: the plane's normal or the axis direction (sign irrelevant).
    point: (3,) mm: a point of the contact (plane) or of the axis line.
    """

    kind: str
    direction: FloatArray
    point: FloatArray


@dataclass(frozen=True)
class Joint:
    """The joint between two parts.

    kinematic: pure degree-of-freedom answer (``FASTENED`` ... ``OTHER``); dof: 0 to 6.
    axis: (3,) unit, canonical sign: rotation axis (revolute, cylindrical), sliding direction
    (slider), plane normal (planar); None for fastened and other. origin: (3,) mm: on the axis
    (revolute, cylindrical: its point closest to the mean contact point), else that mean point.
    suggested: what a CAD user would set (see module docstring); reason: why, in words.
    """

    kinematic: str
    dof: int
    axis: FloatArray | None
    origin: FloatArray
    suggested: str
    reason: str

    def cad_names(self) -> dict[str, str | None]:
        """Names of the suggested joint in Onshape, FreeCAD Assembly and Fusion 360."""
        names = CAD_NAMES.get(self.suggested, {})
        return {k: names.get(k) for k in ("onshape", "freecad", "fusion360")}


def derive_joint(
    constraints: Sequence[Constraint],
    names: tuple[str, str] = ("", ""),
    tol: Tolerances = DEFAULT_TOLERANCES,
) -> Joint | None:
    """The joint allowed by a pair's face mates.

    Args:
        constraints: the pair's coincident contacts and fits, assembly frame, mm.
        names: the two parts' names, for the fastener rule of the suggestion.
        tol: ``parallel_deg`` sets the rank threshold (see module docstring).

    Returns:
        The joint, or None when there is no constraint.
    """
    if not constraints:
        return None
    kinematic, dof, axis, origin = classify_motion(constraints, tol)
    suggested, reason = suggest_joint(kinematic, names)
    return Joint(kinematic, dof, axis, origin, suggested, reason)


def suggest_joint(kinematic: str, names: tuple[str, str]) -> tuple[str, str]:
    """(suggested joint, reason): ``fastened`` for fasteners by name, else the kinematic one."""
    for name in names:
        match = FASTENER_NAME.search(name or "")
        if match and kinematic != FASTENED:
            return FASTENED, (f"{kinematic} by geometry; '{name}' is a fastener by name "
                              f"('{match.group(0)}'): threads are not modelled, CAD users fasten")
    return kinematic, f"{kinematic} by geometry"


def classify_motion(
    constraints: Sequence[Constraint], tol: Tolerances = DEFAULT_TOLERANCES
) -> tuple[str, int, FloatArray | None, FloatArray]:
    """(kinematic name, dof, axis, origin) of the motions the constraints allow.

    Lengths are scaled by the spread of the contact points so that rotations (rad) and
    translations (mm) weigh alike in the SVD; the result is covariant under rigid motions.
    """
    points = np.array([c.point for c in constraints], dtype=np.float64)
    centre = points.mean(axis=0)
    scale = max(1.0, float(np.max(np.linalg.norm(points - centre, axis=1))))
    rows = np.vstack([_rows(c, centre, scale) for c in constraints])
    eps = math.sin(math.radians(tol.parallel_deg))
    _, s, vt = np.linalg.svd(rows)
    rank = int(np.sum(s > eps))
    null = vt[rank:].T  # (6, dof): columns (w * scale, v)
    return _name_motion(null, centre, scale, eps)


def _rows(c: Constraint, centre: FloatArray, scale: float) -> FloatArray:
    """Equations on the twist x = (w * scale, v at ``centre``), each row a unit-scale (6,)."""
    d = np.asarray(c.direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    t1, t2 = _perpendicular_pair(d)
    r = (np.asarray(c.point, dtype=np.float64) - centre) / scale
    zero = np.zeros(3)
    tilt = [np.r_[t1, zero], np.r_[t2, zero]]  # w has no component across d
    # velocity of the point along u: u . v + w . (r x u)
    if c.kind == PLANE:
        return np.array([*tilt, np.r_[np.cross(r, d), d]])
    if c.kind == AXIS:
        return np.array([*tilt, np.r_[np.cross(r, t1), t1], np.r_[np.cross(r, t2), t2]])
    raise ValueError(f"unknown constraint kind {c.kind!r}")


def _perpendicular_pair(d: FloatArray) -> tuple[FloatArray, FloatArray]:
    helper = np.eye(3)[int(np.argmin(np.abs(d)))]
    t1 = np.cross(d, helper)
    t1 /= np.linalg.norm(t1)
    return t1, np.cross(d, t1)


def _name_motion(
    null: FloatArray, centre: FloatArray, scale: float, eps: float
) -> tuple[str, int, FloatArray | None, FloatArray]:
    """Name the allowed-twist space ``null`` (6, k) (see the table in the module docstring)."""
    dof = null.shape[1]
    if dof == 0:
        return FASTENED, 0, None, centre
    w_block, v_block = null[:3], null[3:]
    u, sw, vh = np.linalg.svd(w_block)
    n_rot = int(np.sum(sw > eps))
    if dof == 1:
        w, v = w_block[:, 0], v_block[:, 0]
        if n_rot == 0:
            return SLIDER, 1, canonical_direction(v), centre
        axis = w / np.linalg.norm(w)
        if abs(float(np.dot(axis, v))) <= eps:
            return REVOLUTE, 1, canonical_direction(axis), _axis_point(w, v, centre, scale)
        return OTHER, 1, None, centre
    if n_rot != 1 or dof not in (2, 3):
        return OTHER, dof, None, centre
    axis = u[:, 0]
    slides = v_block @ vh[1:].T  # (3, dof - 1): the pure translations
    slides = slides / np.linalg.norm(slides, axis=0)
    along = np.abs(axis @ slides)
    if dof == 2 and along[0] >= 1.0 - eps:
        rot = null @ vh[0]
        origin = _axis_point(rot[:3], rot[3:], centre, scale)
        return CYLINDRICAL, 2, canonical_direction(axis), origin
    if dof == 3 and np.all(along <= eps):
        return PLANAR, 3, canonical_direction(axis), centre
    return OTHER, dof, None, centre


def _axis_point(w: FloatArray, v: FloatArray, centre: FloatArray, scale: float) -> FloatArray:
    """Point of the instantaneous rotation axis closest to ``centre``, mm."""
    return centre + scale * np.cross(w, v) / float(np.dot(w, w))


# ---------------------------------------------------------------- contact


@dataclass(frozen=True)
class ContactProxy:
    """What the contact test needs of one solid (assembly frame, mm).

    faces: in ``indexed_faces`` order; boxes: (k, 6) their axis-aligned boxes (lo, hi);
    cheap: (k,) bool, faces whose exact distances are quick (planes); samples: per face, points
    (n, 3) on a coarse mesh of it (None when the mesher skipped the face); slack: mm, the most
    a point of the part's surface can be away from its nearest sample.
    """

    shape: TopoDS_Shape
    faces: list[TopoDS_Face]
    boxes: FloatArray
    cheap: np.ndarray
    samples: list[FloatArray | None]
    slack: float


def contact_proxy(shape: TopoDS_Shape, cheap_ids: Sequence[int] = ()) -> ContactProxy:
    """Face boxes and mesh samples of a solid; the solid itself is not modified (a copy is meshed).

    Args:
        shape: a solid in the assembly frame, mm.
        cheap_ids: ids of faces whose exact distances are quick to compute (planar faces).
    """
    faces = indexed_faces(shape)
    boxes = np.empty((len(faces), 6))
    for k, face in enumerate(faces):
        box = Bnd_Box()
        BRepBndLib.Add_s(face, box, False)
        boxes[k] = box.Get()
    size = float(np.linalg.norm(boxes[:, 3:].max(axis=0) - boxes[:, :3].min(axis=0)))
    deflection = max(MESH_DEFLECTION_MM, size / MESH_RELATIVE)
    spacing = max(SAMPLE_SPACING_MM, size / SAMPLE_RELATIVE)
    copy = BRepBuilderAPI_Copy(shape, False, False).Shape()
    BRepMesh_IncrementalMesh(copy, deflection, False, 0.5, False)
    samples: list[FloatArray | None] = []
    for face in indexed_faces(copy):
        corners = _triangles(face)
        samples.append(None if corners is None else _bisect(corners, spacing).mean(axis=1))
    cheap = np.isin(np.arange(len(faces)), list(cheap_ids))
    slack = 2.0 * spacing / 3.0 + MESH_SAFETY * deflection
    return ContactProxy(shape, faces, boxes, cheap, samples, slack)


def in_contact(a: ContactProxy, b: ContactProxy, tol_mm: float) -> bool:
    """True when the exact distance between the two solids is at most ``tol_mm``.

    Candidate face pairs have boxes within reach; the mesh samples give each a lower bound on
    its distance, and those that may be within ``tol_mm`` are measured exactly (planar pairs
    first, then by the bound), stopping at the first hit. Solids whose boundaries stay apart
    touch only when one holds the other.
    """
    gap = np.maximum(b.boxes[None, :, :3] - a.boxes[:, None, 3:],
                     a.boxes[:, None, :3] - b.boxes[None, :, 3:])
    box_dist = np.linalg.norm(np.clip(gap, 0.0, None), axis=2)
    bound: dict[tuple[int, int], float] = {}
    trees: dict[int, cKDTree] = {}
    slack = a.slack + b.slack
    for i, j in zip(*np.nonzero(box_dist <= tol_mm), strict=True):
        sa, sb = a.samples[i], b.samples[j]
        if sa is None or sb is None:
            bound[(int(i), int(j))] = 0.0
            continue
        if j not in trees:
            trees[j] = cKDTree(sb)
        tree = trees[j]
        nearest, _ = tree.query(sa, k=1, distance_upper_bound=tol_mm + slack)
        if np.isfinite(nearest).any():
            bound[(int(i), int(j))] = float(nearest.min()) - slack
    ranked = sorted(bound, key=lambda ij: (not (a.cheap[ij[0]] and b.cheap[ij[1]]), bound[ij]))
    return (faces_within(a.faces, b.faces, ranked, tol_mm)
            or _holds(a.shape, b.shape) or _holds(b.shape, a.shape))


def faces_within(faces_a: Sequence[TopoDS_Face], faces_b: Sequence[TopoDS_Face],
                 pairs: Sequence[tuple[int, int]], tol_mm: float) -> bool:
    """True when some listed face pair (ids) is within ``tol_mm`` (exact, in list order)."""
    for i, j in pairs:
        dist = BRepExtrema_DistShapeShape(faces_a[i], faces_b[j])
        if dist.IsDone() and dist.Value() <= tol_mm * (1.0 + 1e-9):
            return True
    return False


def _triangles(face: TopoDS_Face) -> FloatArray | None:
    """(m, 3, 3) corners of the face's mesh triangles in the shape's frame, or None."""
    loc = TopLoc_Location()
    tri = BRep_Tool.Triangulation_s(face, loc)
    if tri is None or tri.NbTriangles() == 0:
        return None
    trsf = loc.Transformation()
    nodes = np.array([tri.Node(i).Transformed(trsf).Coord()
                      for i in range(1, tri.NbNodes() + 1)])
    index = np.array([tri.Triangle(i).Get() for i in range(1, tri.NbTriangles() + 1)]) - 1
    corners: FloatArray = nodes[index]
    return corners


def _bisect(tri: FloatArray, spacing: float) -> FloatArray:
    """Split triangles (m, 3, 3) at the middle of their longest edge until no edge > spacing."""
    done = []
    while len(tri):
        length = np.linalg.norm(tri - np.roll(tri, -1, axis=1), axis=2)  # edge k: corner k, k+1
        short = length.max(axis=1) <= spacing
        done.append(tri[short])
        tri, length = tri[~short], length[~short]
        k = length.argmax(axis=1)
        turn = (k[:, None] + np.arange(3)) % 3  # longest edge first: corners 0-1
        tri = np.take_along_axis(tri, turn[:, :, None], axis=1)
        mid = 0.5 * (tri[:, 0] + tri[:, 1])
        tri = np.concatenate([np.stack([tri[:, 0], mid, tri[:, 2]], axis=1),
                              np.stack([mid, tri[:, 1], tri[:, 2]], axis=1)])
    return np.concatenate(done) if done else np.empty((0, 3, 3))


def _holds(outer: TopoDS_Shape, inner: TopoDS_Shape) -> bool:
    """True when a vertex of ``inner`` lies inside the solid ``outer``."""
    explorer = TopExp_Explorer(inner, TopAbs_VERTEX)
    if not explorer.More():
        return False
    point = BRep_Tool.Pnt_s(TopoDS.Vertex_s(explorer.Current()))
    return bool(BRepClass3d_SolidClassifier(outer, point, 1e-7).State() == TopAbs_IN)
