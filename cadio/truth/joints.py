"""The joint a CAD user would set between two parts, from their face mates.

Each face mate is read as a bilateral kinematic constraint, as CAD mates are (a
coincident mate keeps two faces together in both directions, so a part resting on a plate is
"planar", not "free upwards"). The relative motion of part b with respect to part a is a twist
(w, v): angular velocity w and the velocity v of a reference point c. A constraint allows only the
twists that keep it satisfied:

- coincident planes, outward normal n, contact point p: w parallel to n (no tilting) and no
  velocity of p along n (no lift-off): 3 linear equations;
- a shaft in a bore on the axis line (d, p): w parallel to d and the velocity of p parallel to
  d: 4 equations. A concentric face mate (coaxial faces within
  ``Tolerances.concentric_gap_mm``, "fit" or "clearance") is a shaft in a bore when one face is
  convex and the other concave, both cylinders or both cones of one semi-angle, the shaft's
  radius at most the bore's (``fit_radius_mm`` of interference allowed), engaged along the axis
  by more than ``contact_mm``. So a bolt in an ISO 273 fine or medium clearance hole (radial
  clearance up to 1 mm to M24) keeps its axis; in a coarse hole its faces are no mate and only
  its head's contact holds it. Two coaxial holes, two shafts, a gland beside a shaft across
  fillets (faces apart along the axis), a shaft against a chamfer (cylinder and cone) constrain
  nothing;
- a cone seated in a cone (a "fit": one semi-angle, radii within ``fit_radius_mm``) also stops
  motion along the axis, read both ways as a planar contact is: one more equation, so a
  countersunk screw in its seat turns like a bolt under its head.

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

from cadio.records import FloatArray, canonical_direction, perpendicular_pair
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
# Names of parts that CAD users fasten whatever the geometry allows (threads are not modelled).
FASTENER_NAME = re.compile(r"bolt|screw|nut|washer|rivet|stud", re.IGNORECASE)
NONE = "none"


def predicted_joint(concentric: bool, coincident: bool) -> str:
    """The joint two predicted relations imply: a shaft in a bore that also rests on a face
    turns (revolute), one that does not also slides (cylindrical), a face on a face is planar.
    The report scores it against the CAD's kinematic joint; the export writes it back."""
    if concentric:
        return REVOLUTE if coincident else CYLINDRICAL
    return PLANAR if coincident else NONE


@dataclass(frozen=True)
class Constraint:
    """One face mate as a kinematic constraint, in the assembly frame.

    kind: "plane" (a planar contact, or the axial stop of a seated cone) or "axis" (a shaft in
    a bore).
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
        constraints: the pair's planar contacts and shafts in bores, assembly frame, mm.
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
    rows, centre, scale = motion_equations(constraints)
    eps = math.sin(math.radians(tol.parallel_deg))
    _, s, vt = np.linalg.svd(rows)
    rank = int(np.sum(s > eps))
    null = vt[rank:].T  # (6, dof): columns (w * scale, v)
    return _name_motion(null, centre, scale, eps)


def motion_equations(constraints: Sequence[Constraint]) -> tuple[FloatArray, FloatArray, float]:
    """(rows, centre, scale): the linear equations the constraints set on a twist x = (w *
    scale, v at ``centre``), one unit-scale row (6,) each; ``centre`` is the mean constraint
    point and ``scale`` (mm, at least 1) their spread. The null space of ``rows`` is the
    allowed motion."""
    points = np.array([c.point for c in constraints], dtype=np.float64)
    centre = points.mean(axis=0)
    scale = max(1.0, float(np.max(np.linalg.norm(points - centre, axis=1))))
    return np.vstack([_rows(c, centre, scale) for c in constraints]), centre, scale


def _rows(c: Constraint, centre: FloatArray, scale: float) -> FloatArray:
    """Equations on the twist x = (w * scale, v at ``centre``), each row a unit-scale (6,)."""
    d = np.asarray(c.direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    t1, t2 = perpendicular_pair(d)
    r = (np.asarray(c.point, dtype=np.float64) - centre) / scale
    zero = np.zeros(3)
    tilt = [np.r_[t1, zero], np.r_[t2, zero]]  # w has no component across d
    # velocity of the point along u: u . v + w . (r x u)
    if c.kind == PLANE:
        return np.array([*tilt, np.r_[np.cross(r, d), d]])
    if c.kind == AXIS:
        return np.array([*tilt, np.r_[np.cross(r, t1), t1], np.r_[np.cross(r, t2), t2]])
    raise ValueError(f"unknown constraint kind {c.kind!r}")


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

