"""The ten spatial relations of an ordered pair of parts (DESIGN.md, "Relations").

One definition serves the ground truth of scenes and assemblies and the geometric baseline:
``relate`` takes two ``Features`` already placed in one world frame (mm) and what the pair's
face-level mates say (``PairContact``) and returns a ``RelationResult`` with the ten truth
values, which of them sit near a tolerance, the evidence and the tolerances used.

- Directional (left ... behind): the vector from b's centroid to a's lies within
  ``direction_cone_deg`` of the axis. Frame: Z is up; the view axis (the camera's forward
  direction on the ground; +Y for CAD without a camera) is ``behind``, ``front`` its opposite,
  ``right = view x Z`` (+X when the view axis is +Y), ``left`` its opposite.
- ``coincident`` / ``concentric``: the pair has a face-level coincident / concentric mate.
  The truth measures them on the exact faces (``cadio.truth.labels.label_placed``, which
  shares the computation with the assemblies' mates) and hands them in; without them
  ``estimate_contact`` reads them off the features alone (primitives fitted to points have no
  faces to intersect), an estimate that is no truth.
- ``parallel``: the dominant plane directions (``Features.dominant_plane``) lie within
  ``parallel_deg`` and the pair is not coincident; ``perpendicular``: they lie at 90 +/-
  ``parallel_deg``. A part without a dominant direction makes both False and near the boundary.

The paper's logic rules hold by construction: the directional relations are computed on a
canonical ordering of the pair and those of the swapped pair are the converse ones, so
``left(a, b) iff right(b, a)`` exactly; the others are symmetric. Values exactly at a tolerance
count as inside (with a 1e-9 relative allowance for rounding).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
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
    "centre_distance_mm", "plane_angle_deg", "coincident_gap_mm", "concentric_gap_mm",
    "coincident_near", "concentric_near", "plane_undefined", "direction_undefined",
    "contact_measured",
)
# Centroids closer than this (mm) give no direction: the directional relations are undefined.
_MIN_OFFSET_MM = 1e-9


@dataclass(frozen=True)
class BoundaryMargins:
    """How close to a tolerance a pair is "near the boundary" (the scene generator's margins).

    A near-boundary answer could flip with a hair of noise; reports keep such pairs apart. For
    the face mates a relation is near when its answer differs between the tolerances loosened
    and tightened by these margins (``loose_tolerances``, ``tight_tolerances``).
    """

    direction_deg: float = 1.0  # 14 to 16 degrees around the 15 degree cone
    plane_deg: float = 0.1  # 0.9 to 1.1 degrees (parallel), 88.9 to 89.1 (perpendicular)
    mate_deg: float = 0.1  # opposed normals and coaxial lines, 0.4 to 0.6 degrees
    offset_factor: float = 2.0  # contact offsets and axis-line distances up to twice the limit
    gap_fraction: float = 0.2  # coaxial faces 0.8 to 1.2 mm apart around the 1 mm limit
    # Offsets up to this are exact contact or coaxiality (B-rep rounding, freeform fits within
    # ``freeform_fit_mm``), not near misses.
    exact_mm: float = 1e-3
    # A dominant plane direction whose runner-up carries within this fraction of the limit
    # (1/1.5 of its area, so 0.6 to 0.73) is no stable choice.
    dominance_fraction: float = 0.1


DEFAULT_MARGINS = BoundaryMargins()


def loose_tolerances(tol: Tolerances, margins: BoundaryMargins = DEFAULT_MARGINS) -> Tolerances:
    """The face mates' tolerances widened to the outer edge of the margins."""
    return tol.with_overrides({
        "mate_angle_deg": tol.mate_angle_deg + margins.mate_deg,
        "coaxial_deg": tol.coaxial_deg + margins.mate_deg,
        "contact_mm": tol.contact_mm * margins.offset_factor,
        "coaxial_mm": tol.coaxial_mm * margins.offset_factor,
        "concentric_gap_mm": tol.concentric_gap_mm * (1.0 + margins.gap_fraction)})


def tight_tolerances(tol: Tolerances, margins: BoundaryMargins = DEFAULT_MARGINS) -> Tolerances:
    """The face mates' tolerances narrowed to the inner edge of the margins."""
    return tol.with_overrides({
        "mate_angle_deg": max(0.0, tol.mate_angle_deg - margins.mate_deg),
        "coaxial_deg": max(0.0, tol.coaxial_deg - margins.mate_deg),
        "contact_mm": min(tol.contact_mm, margins.exact_mm),
        "coaxial_mm": min(tol.coaxial_mm, margins.exact_mm),
        "concentric_gap_mm": tol.concentric_gap_mm * (1.0 - margins.gap_fraction)})


@dataclass(frozen=True)
class PairContact:
    """What the face-level mates of a pair say, as the part relations read them (symmetric).

    coincident, concentric: the pair has a coincident / concentric face mate.
    *_near: that answer differs between the loosened and the tightened tolerances.
    coincident_gap_mm: the smallest plane offset of opposed planar faces that overlap (or, for
        an estimate, of opposed planes), mm; NaN when none was within reach.
    concentric_gap_mm: the smallest exact distance of two coaxial faces, mm; NaN likewise.
    measured: decided on the exact faces (the truth), not estimated from features.
    """

    coincident: bool = False
    concentric: bool = False
    coincident_near: bool = False
    concentric_near: bool = False
    coincident_gap_mm: float = math.nan
    concentric_gap_mm: float = math.nan
    measured: bool = True

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN as None); ``from_dict`` inverts it."""
        return {k: (None if isinstance(v, float) and math.isnan(v) else v)
                for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PairContact:
        """From ``to_dict``, or from a row of a scene table (``to_row``'s columns)."""
        def gap(key: str) -> float:
            value = d.get(key)
            return math.nan if value is None else float(value)

        return cls(bool(d["coincident"]), bool(d["concentric"]),
                   bool(d.get("coincident_near", False)), bool(d.get("concentric_near", False)),
                   gap("coincident_gap_mm"), gap("concentric_gap_mm"),
                   bool(d.get("measured", d.get("contact_measured", True))))


NO_CONTACT = PairContact()


@dataclass(frozen=True)
class RelationResult:
    """Truth of the ten relations of the ordered pair (a, b), with the evidence.

    truth: one bool per relation, in ``Relation`` order.
    near: per relation, whether its answer sits within the margins of a tolerance (for this
        view: the directional ones depend on it).
    direction_deg: angle between the vector from b's centroid to a's and each directional axis,
        in ``DIRECTIONAL`` order, degrees (NaN when the centroids coincide).
    centre_distance_mm: distance between the centroids, mm.
    plane_angle_deg: angle between the dominant plane directions, [0, 90] degrees (None when a
        part has none: ``plane_undefined``).
    contact: the face mates' answer (measured, or estimated from the features).
    direction_undefined: the centroids coincide, so the directional relations are False.
    """

    truth: tuple[bool, ...]
    near: tuple[bool, ...]
    direction_deg: tuple[float, ...]
    centre_distance_mm: float
    plane_angle_deg: float | None
    contact: PairContact
    direction_undefined: bool
    plane_undefined: bool
    view_axis: tuple[float, float, float]
    tolerances: Tolerances
    margins: BoundaryMargins = field(default=DEFAULT_MARGINS)

    def __getitem__(self, relation: Relation | str) -> bool:
        return self.truth[RELATIONS.index(Relation(relation))]

    def holding(self) -> tuple[Relation, ...]:
        """The relations that hold, in ``Relation`` order."""
        return tuple(r for r, t in zip(RELATIONS, self.truth, strict=True) if t)

    def near_boundary(self) -> bool:
        """Whether any relation sits near its boundary."""
        return any(self.near)

    def to_row(self) -> dict[str, Any]:
        """A flat dict: one bool per relation name, then the evidence (NaN where undefined)."""
        nan = float("nan")
        c = self.contact
        row: dict[str, Any] = relation_table(self)
        row.update(
            centre_distance_mm=self.centre_distance_mm,
            plane_angle_deg=nan if self.plane_angle_deg is None else self.plane_angle_deg,
            coincident_gap_mm=c.coincident_gap_mm, concentric_gap_mm=c.concentric_gap_mm,
            coincident_near=c.coincident_near, concentric_near=c.concentric_near,
            plane_undefined=self.plane_undefined, direction_undefined=self.direction_undefined,
            contact_measured=c.measured,
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
    contact: PairContact | None = None,
    margins: BoundaryMargins = DEFAULT_MARGINS,
) -> RelationResult:
    """The ten relations of the ordered pair (a, b), both placed in the world frame.

    Args:
        a, b: features in one world frame, mm (``Features.transformed(pose)`` of each part).
        view_axis: (3,) the observer's forward direction; +Y for CAD without a camera.
        tol: the tolerances; reported in the result.
        contact: the pair's face mates as measured on the exact faces (the truth); None
            estimates them from the features (``estimate_contact``).
        margins: what counts as near a tolerance (the directional and plane relations; the
            contact's own flags were set when it was measured).

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
    angles = tuple(float(angle_by[r]) for r in DIRECTIONAL)
    contact = estimate_contact(a, b, tol) if contact is None else contact
    plane = _plane_angle(a, b)
    parallel = plane is not None and bool(_inside(plane, tol.parallel_deg)) \
        and not contact.coincident
    perpendicular = plane is not None and bool(_inside(90.0 - plane, tol.parallel_deg))
    truth = (*(bool(direction[r]) for r in DIRECTIONAL),
             parallel, perpendicular, contact.concentric, contact.coincident)
    return RelationResult(
        truth=truth,
        near=_near(angles, plane, a, b, contact, tol, margins),
        direction_deg=angles,
        centre_distance_mm=float(np.linalg.norm(first.centroid - second.centroid)),
        plane_angle_deg=plane, contact=contact,
        direction_undefined=bool(np.isnan(angles6).all()), plane_undefined=plane is None,
        view_axis=(float(view_axis[0]), float(view_axis[1]), float(view_axis[2])),
        tolerances=tol, margins=margins,
    )


def near_boundary(result: RelationResult) -> bool:
    """Whether any of the pair's relations sits within the margins of its tolerance."""
    return result.near_boundary()


def _near(angles: tuple[float, ...], plane: float | None, a: Features, b: Features,
          contact: PairContact, tol: Tolerances, margins: BoundaryMargins) -> tuple[bool, ...]:
    """Per relation: within the margins of its tolerance."""
    directional = tuple(math.isfinite(x) and abs(x - tol.direction_cone_deg)
                        <= margins.direction_deg for x in angles)
    if plane is None or any(_unstable(f, tol, margins) for f in (a, b)):
        parallel = perpendicular = True
    else:
        parallel = abs(plane - tol.parallel_deg) <= margins.plane_deg or bool(
            _inside(plane, tol.parallel_deg) and contact.coincident_near)
        perpendicular = abs(90.0 - plane - tol.parallel_deg) <= margins.plane_deg
    return (*directional, parallel, perpendicular, contact.concentric_near,
            contact.coincident_near)


def _unstable(f: Features, tol: Tolerances, margins: BoundaryMargins) -> bool:
    """The part's dominant plane direction is a near thing (its runner-up's share of the
    largest's area lies within the margin of 1 / ``dominant_area_ratio``)."""
    limit = 1.0 / tol.dominant_area_ratio
    return f.dominant_plane is not None and f.dominant_runner_up > 0.0 and \
        abs(f.dominant_runner_up - limit) <= margins.dominance_fraction * limit


def _inside(value: Any, limit: float) -> Any:
    """value <= limit, allowing rounding of 1e-9 relative (values at a tolerance are inside)."""
    return np.asarray(value) <= limit + _REL_EPS * max(abs(limit), 1.0)


def _line_angle_deg(u: FloatArray, v: FloatArray) -> float:
    """Angle between two undirected lines, [0, 90] degrees (well conditioned near 0 and 90)."""
    cross = float(np.linalg.norm(np.cross(u, v)))
    return math.degrees(math.atan2(cross, abs(float(np.dot(u, v)))))


def _plane_angle(a: Features, b: Features) -> float | None:
    if a.dominant_plane is None or b.dominant_plane is None:
        return None
    return _line_angle_deg(a.dominant_plane, b.dominant_plane)


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


# ---------------------------------------------------------------- the estimate from features


def estimate_contact(a: Features, b: Features,
                     tol: Tolerances = DEFAULT_TOLERANCES) -> PairContact:
    """The face mates of a pair as the features alone suggest them (no faces to measure).

    coincident: the parts' boxes lie within ``contact_mm`` and two opposed planes (outward
    normals within ``mate_angle_deg`` of opposite) lie within ``coplanar_mm``; concentric: the
    boxes lie within ``concentric_gap_mm`` and two axis groups are coaxial (``coaxial_deg``,
    ``coaxial_mm``). Without the faces' extents this over-reads (two planes may face each
    other beside one another), and the axis-aligned boxes it reads grow when a part turns:
    the truth measures the faces instead.
    """
    gap = _box_gap(a, b)
    ref = 0.5 * (a.centroid + b.centroid)
    plane_gap = min((_opposed_gap(ga, gb, ref) for ga in a.planes for gb in b.planes
                     if _line_angle_deg(ga.normal, gb.normal) <= tol.mate_angle_deg
                     + _REL_EPS), default=math.nan)
    coincident = bool(gap <= tol.contact_mm and _inside(plane_gap, tol.coplanar_mm))
    coaxial = any(_coaxial(xa, xb, ref, tol) for xa in a.axes for xb in b.axes)
    return PairContact(coincident=coincident,
                       concentric=bool(coaxial and gap <= tol.concentric_gap_mm),
                       coincident_gap_mm=plane_gap, measured=False)


def _box_gap(a: Features, b: Features) -> float:
    """Distance between the parts' axis-aligned boxes, mm (0 when they overlap)."""
    sep = np.maximum(b.bbox_min - a.bbox_max, a.bbox_min - b.bbox_max)
    return float(np.linalg.norm(np.clip(sep, 0.0, None)))


def _opposed_gap(ga: PlaneGroup, gb: PlaneGroup, ref: FloatArray) -> float:
    """Smallest offset (mm) between an a-face and a b-face whose outward normals oppose, each
    plane's signed distance taken from ``ref`` along its own normal (rigid-motion invariant);
    NaN when no such pair exists."""
    sign = 1.0 if float(np.dot(ga.normal, gb.normal)) >= 0.0 else -1.0
    sa = float(np.dot(ga.normal, ref)) - np.asarray(ga.offsets, dtype=np.float64)
    sb = sign * (float(np.dot(gb.normal, ref)) - np.asarray(gb.offsets, dtype=np.float64))
    opposed = np.outer(ga.outward, gb.outward) * sign < 0
    gaps = np.abs(sa[:, None] - sb[None, :])[opposed]
    return float(gaps.min()) if gaps.size else math.nan


def _coaxial(xa: AxisGroup, xb: AxisGroup, ref: FloatArray, tol: Tolerances) -> bool:
    return bool(_inside(_line_angle_deg(xa.direction, xb.direction), tol.coaxial_deg)
                and _inside(_line_distance(xa, xb, ref), tol.coaxial_mm))


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


# ---------------------------------------------------------------- stored truth


def contacts_of_mates(rows: Iterable[Mapping[str, Any]], near: Iterable[Sequence[str]] = ()
                      ) -> dict[tuple[str, str], PairContact]:
    """The face mates' answer per unordered pair of an assembly's mates table.

    Args:
        rows: the table's rows (part_a, part_b, level, relation); its part-level concentric
            and coincident rows are the pairs' face mates.
        near: (part_a, part_b, relation) of the answers near a boundary (the table's
            ``attrs["near_boundary"]``).

    Returns:
        (part_a, part_b) and (part_b, part_a) -> PairContact, for every pair with a part-level
        concentric or coincident row or a near answer; any other pair has ``NO_CONTACT``.
    """
    found: dict[frozenset[str], dict[str, bool]] = {}
    for r in rows:
        if r["level"] == "part" and r["relation"] in ("concentric", "coincident"):
            found.setdefault(frozenset((str(r["part_a"]), str(r["part_b"]))), {})[
                str(r["relation"])] = True
    for a, b, relation in near:
        found.setdefault(frozenset((str(a), str(b))), {})[f"{relation}_near"] = True
    out = {}
    for key, flags in found.items():
        contact = PairContact(**{k: flags.get(k, False) for k in (
            "coincident", "concentric", "coincident_near", "concentric_near")})
        a, b = sorted(key)
        out[(a, b)] = out[(b, a)] = contact
    return out
