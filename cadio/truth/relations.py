"""The ten spatial relations of an ordered pair of parts, from their geometric features.

One definition (DESIGN.md, "Relations") serves the B-rep ground truth and the geometric
baseline alike: ``relate`` takes two ``Features`` already placed in one world frame (mm) and
returns a ``RelationResult`` with the ten truth values, the evidence that decided them and the
tolerances used.

Frame: Z is up. The view axis (the camera's forward direction projected on the ground; +Y for
CAD without a camera) is ``behind``; ``front`` is its opposite; ``right = view x Z`` (so +X when
the view axis is +Y), ``left`` its opposite; ``above`` = +Z, ``below`` = -Z.

The paper's logic rules hold by construction: the symmetric relations and all evidence are
computed on a canonical ordering of the pair, and the directional relations of the swapped
pair are the converse ones (left <-> right, ...), so ``left(a, b) iff right(b, a)`` exactly.
Values exactly at a tolerance count as inside (with a 1e-9 relative allowance for rounding).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from cadio.records import (
    CONVERSE,
    DIRECTIONAL,
    AxisGroup,
    Features,
    FloatArray,
    PlaneGroup,
    Relation,
)
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances

RELATIONS = tuple(Relation)
Vector3 = Sequence[float] | FloatArray  # a (3,) direction
CAD_VIEW_AXIS = (0.0, 1.0, 0.0)
# Relative allowance so that a value computed exactly at a tolerance is not lost to rounding.
_REL_EPS = 1e-9
# Evidence columns of ``RelationResult.to_row`` after the ten relation names (NaN = undefined).
EVIDENCE_COLUMNS = (
    "centre_distance_mm", "plane_angle_deg", "plane_gap_mm", "axis_angle_deg", "axis_distance_mm",
    "plane_undefined", "axis_undefined", "direction_undefined", "plane_tie", "axis_tie",
)
# Centroids closer than this (mm) give no direction: the directional relations are undefined.
_MIN_OFFSET_MM = 1e-9
# Offsets below this (mm) are exact contact or coaxiality, not a near miss of a tolerance.
_EXACT_MM = 1e-6


@dataclass(frozen=True)
class RelationResult:
    """Truth of the ten relations of the ordered pair (a, b), with the evidence.

    truth: one bool per relation, in ``Relation`` order.
    direction_deg: angle between the vector from b's centroid to a's and each directional axis,
        in ``DIRECTIONAL`` order, degrees (NaN when the centroids coincide).
    centre_distance_mm: distance between the centroids, mm.
    plane_angle_deg: angle between the principal plane directions, [0, 90] degrees.
    plane_gap_mm: smallest offset between a principal face of a and one of b, measured along the
        normals at the midpoint of the centroids (only when the directions agree within
        ``parallel_deg``), mm.
    coplanar_faces: face ids (of a, of b) of that closest pair.
    coplanar_opposed: their outward normals point at each other or away (face-to-face).
    axis_angle_deg, axis_distance_mm: angle between the principal axes (degrees) and distance
        between the axis lines at the midpoint of the centroids (mm).
    axis_faces: face ids of the principal axis groups (of a, of b).
    *_undefined: a part lacks the feature (or the centroids coincide), so the relations that need
        it are False. *_tie: a part's principal choice was a tie (flag from ``Features``).
    """

    truth: tuple[bool, ...]
    direction_deg: tuple[float, ...]
    centre_distance_mm: float
    plane_angle_deg: float | None
    plane_gap_mm: float | None
    coplanar_faces: tuple[int, int] | None
    coplanar_opposed: bool | None
    axis_angle_deg: float | None
    axis_distance_mm: float | None
    axis_faces: tuple[tuple[int, ...], tuple[int, ...]] | None
    direction_undefined: bool
    plane_undefined: bool
    axis_undefined: bool
    plane_tie: bool
    axis_tie: bool
    view_axis: tuple[float, float, float]
    tolerances: Tolerances

    def __getitem__(self, relation: Relation | str) -> bool:
        return self.truth[RELATIONS.index(Relation(relation))]

    def holding(self) -> tuple[Relation, ...]:
        """The relations that hold, in ``Relation`` order."""
        return tuple(r for r, t in zip(RELATIONS, self.truth, strict=True) if t)

    def to_row(self) -> dict[str, Any]:
        """A flat dict: one bool per relation name, then evidence (NaN where undefined)."""
        nan = float("nan")
        row: dict[str, Any] = relation_table(self)
        row.update(
            centre_distance_mm=self.centre_distance_mm,
            plane_angle_deg=nan if self.plane_angle_deg is None else self.plane_angle_deg,
            plane_gap_mm=nan if self.plane_gap_mm is None else self.plane_gap_mm,
            axis_angle_deg=nan if self.axis_angle_deg is None else self.axis_angle_deg,
            axis_distance_mm=nan if self.axis_distance_mm is None else self.axis_distance_mm,
            plane_undefined=self.plane_undefined, axis_undefined=self.axis_undefined,
            direction_undefined=self.direction_undefined,
            plane_tie=self.plane_tie, axis_tie=self.axis_tie,
        )
        assert tuple(row)[len(RELATIONS):] == EVIDENCE_COLUMNS
        return row


def relation_table(result: RelationResult) -> dict[str, bool]:
    """The ten truth values keyed by relation name ("left" ... "coincident")."""
    return {r.value: t for r, t in zip(RELATIONS, result.truth, strict=True)}


def view_frame(view_axis: Vector3 = CAD_VIEW_AXIS) -> FloatArray:
    """Rows right, behind, up (3, 3) unit vectors of the observer's frame.

    Raises:
        ValueError: the view axis has no horizontal component (looking straight up or down).
    """
    v = np.array([view_axis[0], view_axis[1], 0.0], dtype=np.float64)
    norm = float(np.linalg.norm(v))
    if norm < 1e-12 or not math.isfinite(norm):
        raise ValueError(f"view axis {tuple(view_axis)} has no horizontal direction")
    behind = v / norm
    right = np.array([behind[1], -behind[0], 0.0])  # behind x Z
    return np.stack([right, behind, np.array([0.0, 0.0, 1.0])])


def direction_axes(view_axis: Vector3 = CAD_VIEW_AXIS) -> FloatArray:
    """The six directional axes (6, 3) in ``DIRECTIONAL`` order; opposite axes negate exactly."""
    right, behind, up = view_frame(view_axis)
    return np.stack([-right, right, up, -up, -behind, behind])


def directional_truth(
    offsets: FloatArray,
    view_axis: Vector3 = CAD_VIEW_AXIS,
    tol: Tolerances = DEFAULT_TOLERANCES,
) -> tuple[np.ndarray, FloatArray]:
    """Batch directional relations from centroid offsets.

    Args:
        offsets: (n, 3) float64, mm: centroid of a minus centroid of b for each pair.
        view_axis: (3,) the observer's forward direction (only its horizontal part is used).
        tol: tolerances; ``direction_cone_deg`` is the half-angle of each cone.

    Returns:
        truth (n, 6) bool and angles (n, 6) float64 degrees, in ``DIRECTIONAL`` order; rows with
        a zero offset are all False with NaN angles.

    Raises:
        ValueError: bad view axis, or a cone of 90 degrees or more (rule (5) would break).
    """
    if not 0.0 < tol.direction_cone_deg < 90.0:
        raise ValueError(f"direction_cone_deg must be in (0, 90), got {tol.direction_cone_deg}")
    d = np.asarray(offsets, dtype=np.float64).reshape(-1, 3)
    axes = direction_axes(view_axis)
    dots = d @ axes.T  # (n, 6)
    crosses = np.linalg.norm(np.cross(d[:, None, :], axes[None, :, :]), axis=-1)  # (n, 6)
    angles = np.degrees(np.arctan2(crosses, dots))
    undefined = np.linalg.norm(d, axis=1) <= _MIN_OFFSET_MM
    angles[undefined] = np.nan
    truth = _inside(angles, tol.direction_cone_deg) & ~undefined[:, None]
    return truth, angles


def relate(
    a: Features,
    b: Features,
    view_axis: Vector3 = CAD_VIEW_AXIS,
    tol: Tolerances = DEFAULT_TOLERANCES,
) -> RelationResult:
    """The ten relations of the ordered pair (a, b), both placed in the world frame.

    Args:
        a, b: features in one world frame, mm (``Features.transformed(pose)`` of each part).
        view_axis: (3,) the observer's forward direction; +Y for CAD without a camera.
        tol: the tolerances; reported in the result.

    Returns:
        A ``RelationResult``; ``result[Relation.LEFT]`` is left(a, b).

    Raises:
        ValueError: the view axis is vertical or the direction cone is 90 degrees or more.
    """
    swapped = _canonical_order(a, b) > 0
    first, second = (b, a) if swapped else (a, b)
    truth6, angles6 = directional_truth((first.centroid - second.centroid)[None, :],
                                        view_axis, tol)
    direction = dict(zip(DIRECTIONAL, truth6[0], strict=True))
    angle_by = dict(zip(DIRECTIONAL, angles6[0], strict=True))
    if swapped:  # r(a, b) iff converse(r)(b, a): read the canonical pair's converse value
        direction = {r: direction[CONVERSE[r]] for r in DIRECTIONAL}
        angle_by = {r: angle_by[CONVERSE[r]] for r in DIRECTIONAL}
    plane = _plane_evidence(first, second, tol)
    axis = _axis_evidence(first, second, tol)
    if swapped:
        plane = plane.swapped()
        axis = axis.swapped()
    truth = (*(bool(direction[r]) for r in DIRECTIONAL),
             plane.parallel, plane.perpendicular, axis.concentric, plane.coincident)
    return RelationResult(
        truth=truth,
        direction_deg=tuple(float(angle_by[r]) for r in DIRECTIONAL),
        centre_distance_mm=float(np.linalg.norm(first.centroid - second.centroid)),
        plane_angle_deg=plane.angle_deg, plane_gap_mm=plane.gap_mm,
        coplanar_faces=plane.faces, coplanar_opposed=plane.opposed,
        axis_angle_deg=axis.angle_deg, axis_distance_mm=axis.distance_mm, axis_faces=axis.faces,
        direction_undefined=bool(np.isnan(angles6).all()),
        plane_undefined=a.principal_plane is None or b.principal_plane is None,
        axis_undefined=a.principal_axis is None or b.principal_axis is None,
        plane_tie=a.principal_plane_tie or b.principal_plane_tie,
        axis_tie=a.principal_axis_tie or b.principal_axis_tie,
        view_axis=(float(view_axis[0]), float(view_axis[1]), float(view_axis[2])),
        tolerances=tol,
    )


def _inside(value: Any, limit: float) -> Any:
    """value <= limit, allowing rounding of 1e-9 relative (values at a tolerance are inside)."""
    return np.asarray(value) <= limit + _REL_EPS * max(abs(limit), 1.0)


def _line_angle_deg(u: FloatArray, v: FloatArray) -> float:
    """Angle between two undirected lines, [0, 90] degrees (well conditioned near 0 and 90)."""
    cross = float(np.linalg.norm(np.cross(u, v)))
    return math.degrees(math.atan2(cross, abs(float(np.dot(u, v)))))


def _feature_key(f: Features) -> tuple[float, ...]:
    return (*f.centroid.tolist(), *f.bbox_min.tolist(), *f.bbox_max.tolist(), f.volume, f.area)


def _canonical_order(a: Features, b: Features) -> int:
    """-1, 0 or 1 as a sorts before, with or after b (a total, deterministic order)."""
    ka, kb = _feature_key(a), _feature_key(b)
    if ka == kb:
        ja = json.dumps(a.to_dict(), sort_keys=True)
        jb = json.dumps(b.to_dict(), sort_keys=True)
        ka, kb = (ja,), (jb,)  # type: ignore[assignment]
    return (ka > kb) - (ka < kb)


@dataclass(frozen=True)
class _PlaneEvidence:
    parallel: bool = False
    perpendicular: bool = False
    coincident: bool = False
    angle_deg: float | None = None
    gap_mm: float | None = None
    faces: tuple[int, int] | None = None
    opposed: bool | None = None

    def swapped(self) -> _PlaneEvidence:
        faces = None if self.faces is None else (self.faces[1], self.faces[0])
        return _PlaneEvidence(self.parallel, self.perpendicular, self.coincident,
                              self.angle_deg, self.gap_mm, faces, self.opposed)


@dataclass(frozen=True)
class _AxisEvidence:
    concentric: bool = False
    angle_deg: float | None = None
    distance_mm: float | None = None
    faces: tuple[tuple[int, ...], tuple[int, ...]] | None = None

    def swapped(self) -> _AxisEvidence:
        faces = None if self.faces is None else (self.faces[1], self.faces[0])
        return _AxisEvidence(self.concentric, self.angle_deg, self.distance_mm, faces)


def principal_plane_group(f: Features) -> PlaneGroup | None:
    """The planar group whose normal is the principal plane direction (None if absent)."""
    if f.principal_plane is None or not f.planes:
        return None
    dots = [abs(float(np.dot(g.normal, f.principal_plane))) for g in f.planes]
    return f.planes[int(np.argmax(dots))]


def _plane_evidence(a: Features, b: Features, tol: Tolerances) -> _PlaneEvidence:
    """parallel / perpendicular / coincident from the principal plane directions and faces."""
    if a.principal_plane is None or b.principal_plane is None:
        return _PlaneEvidence()
    angle = _line_angle_deg(a.principal_plane, b.principal_plane)
    perpendicular = bool(_inside(90.0 - angle, tol.parallel_deg))
    if not _inside(angle, tol.parallel_deg):
        return _PlaneEvidence(perpendicular=perpendicular, angle_deg=angle)
    ga, gb = principal_plane_group(a), principal_plane_group(b)
    if ga is None or gb is None or not ga.offsets or not gb.offsets:
        # Directions agree but there are no faces to be coplanar: parallel by definition.
        return _PlaneEvidence(parallel=True, perpendicular=perpendicular, angle_deg=angle)
    gap, i, j, opposed = _closest_faces(ga, gb, 0.5 * (a.centroid + b.centroid))
    coincident = bool(_inside(gap, tol.coplanar_mm))
    return _PlaneEvidence(
        parallel=not coincident, perpendicular=perpendicular, coincident=coincident,
        angle_deg=angle, gap_mm=gap, faces=(ga.face_ids[i], gb.face_ids[j]), opposed=opposed,
    )


def _closest_faces(
    ga: PlaneGroup, gb: PlaneGroup, ref: FloatArray
) -> tuple[float, int, int, bool]:
    """Smallest plane-to-plane offset between faces of two nearly parallel groups.

    Each plane's signed distance from the reference point ``ref`` (mm) is taken along its own
    normal, with b's normal turned to agree with a's; the offset is their difference. For exactly
    parallel planes this is |d_a - d_b| wherever ``ref`` is; for planes tilted by up to the
    parallel tolerance it is their separation near the pair, and it is rigid-motion invariant.

    Returns:
        (offset mm, face index in a, face index in b, outward normals opposed).
    """
    sign = 1.0 if float(np.dot(ga.normal, gb.normal)) >= 0.0 else -1.0
    sa = float(np.dot(ga.normal, ref)) - np.asarray(ga.offsets, dtype=np.float64)
    sb = sign * (float(np.dot(gb.normal, ref)) - np.asarray(gb.offsets, dtype=np.float64))
    gaps = np.abs(sa[:, None] - sb[None, :])
    i, j = np.unravel_index(int(np.argmin(gaps)), gaps.shape)
    opposed = ga.outward[i] * gb.outward[j] * sign < 0
    return float(gaps[i, j]), int(i), int(j), bool(opposed)


def _axis_evidence(a: Features, b: Features, tol: Tolerances) -> _AxisEvidence:
    """concentric from the principal axes: angle and distance between the axis lines."""
    if a.principal_axis is None or b.principal_axis is None:
        return _AxisEvidence()
    xa, xb = a.principal_axis, b.principal_axis
    angle = _line_angle_deg(xa.direction, xb.direction)
    distance = _line_distance(xa, xb, 0.5 * (a.centroid + b.centroid))
    concentric = bool(_inside(angle, tol.coaxial_deg) and _inside(distance, tol.coaxial_mm))
    return _AxisEvidence(concentric, angle, distance, (xa.face_ids, xb.face_ids))


def _line_distance(xa: AxisGroup, xb: AxisGroup, ref: FloatArray) -> float:
    """Distance (mm) between two nearly parallel axis lines, measured near ``ref``.

    The closest points of each line to ``ref`` are compared across the mean direction: exact for
    parallel lines, and unlike the skew-line distance it does not vanish for lines that cross
    far away at a small angle.
    """
    sign = 1.0 if float(np.dot(xa.direction, xb.direction)) >= 0.0 else -1.0
    pa = xa.point + float(np.dot(ref - xa.point, xa.direction)) * xa.direction
    pb = xb.point + float(np.dot(ref - xb.point, xb.direction)) * xb.direction
    mean = xa.direction + sign * xb.direction
    mean = mean / np.linalg.norm(mean)
    diff = pa - pb
    return float(np.linalg.norm(diff - float(np.dot(diff, mean)) * mean))


@dataclass(frozen=True)
class BoundaryMargins:
    """How close to a tolerance a pair is "near the boundary" (the scene generator's margins).

    A near-boundary pair's truth could flip with a hair of noise; reports keep such pairs apart.
    """

    direction_deg: float = 1.0  # 14 to 16 degrees around the 15 degree cone
    plane_deg: float = 0.1  # 0.9 to 1.1 degrees (parallel), 88.9 to 89.1 (perpendicular)
    offset_factor: float = 2.0  # gaps and axis distances up to twice their tolerance


def near_boundary(result: RelationResult, margins: BoundaryMargins = BoundaryMargins()) -> bool:
    """Whether any of the pair's relations sits within ``margins`` of its tolerance."""
    tol = result.tolerances
    angles = np.asarray(result.direction_deg, dtype=np.float64)
    if np.any(np.abs(angles[np.isfinite(angles)] - tol.direction_cone_deg)
              <= margins.direction_deg):
        return True
    plane = result.plane_angle_deg
    if plane is not None and min(abs(plane - tol.parallel_deg),
                                 abs(90.0 - plane - tol.parallel_deg)) <= margins.plane_deg:
        return True
    gap, distance = result.plane_gap_mm, result.axis_distance_mm
    offsets = [(gap, tol.coplanar_mm), (distance, tol.coaxial_mm)]
    if any(v is not None and _EXACT_MM < v <= margins.offset_factor * limit
           for v, limit in offsets):
        return True  # (exactly touching or coaxial parts, offsets ~0, are not near)
    axis = result.axis_angle_deg
    return axis is not None and abs(axis - tol.coaxial_deg) <= margins.plane_deg
