"""Each CAD mate as built: its residuals from the two parts' registered poses, and its status.

A face mate of the design (a row of the assembly's mates table: two faces, an axis or a normal
and a point, in the assembly's frame) holds as built when the two parts sit relative to each
other as the design puts them, in the directions the mate constrains:

- concentric: the two faces' common axis: the angle between part a's axis and part b's, and
  how far a's axis moved off b's, across the axis (along it the mate says nothing);
- coincident: the two faces' common plane: the angle between their normals, and how far a's
  face moved off b's along the normal (in the plane the mate says nothing).

The residual of each is read from a's pose relative to b's, as built against as designed, so
that a shift of the whole assembly moves no residual. Its threshold is the larger of the mate's
tolerance (``Tolerances``) and three standard deviations of the residual along its own
direction (the offset's across the axis, the axis a tilt turns about), from both parts' pose
uncertainties (``cadio.inspect.uncertainty``): a pin sure across X but not across Y, moved 1 mm
along X, is off its axis. From several views each part is also held against its partner where
the rest of the assembly puts the partner (``cadio.inspect.consensus``). Status: ``holds``,
``broken`` (a residual past its threshold), ``not observable`` (no residual broken, but one of
them lies along a direction the view does not constrain: never a pass) or ``not inspectable``
(a part shows too little of itself, or is missing, which breaks its mates).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from cadio.inspect.uncertainty import PoseUncertainty, point_motion
from cadio.records import FloatArray
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances

if TYPE_CHECKING:
    from cadio.inspect.consensus import Rest

HOLDS, BROKEN, NOT_OBSERVABLE, NOT_INSPECTABLE = (
    "holds", "broken", "not observable", "not inspectable")
STATUSES = (HOLDS, BROKEN, NOT_OBSERVABLE, NOT_INSPECTABLE)
SIGMAS = 3.0  # a residual past this many standard deviations (and the tolerance) is broken


@dataclass(frozen=True)
class PartAsBuilt:
    """A part as the scan shows it: its registered pose (part -> world, mm; None: not found),
    the pose's uncertainty, and why it cannot be inspected (``missing`` or ``too little
    visible``; "" when it can)."""

    index: int
    pose: FloatArray | None
    uncertainty: PoseUncertainty | None
    problem: str = ""


@dataclass(frozen=True)
class Residual:
    """One constrained direction of a mate: its value, threshold and standard deviation along
    the residual's own direction; ``seen``: every direction it spans is observed (an axis
    offset spans both directions across the axis)."""

    name: str
    value: float
    threshold: float
    sigma: float
    seen: bool = True

    @property
    def broken(self) -> bool:
        return self.value > self.threshold

    @property
    def measured(self) -> bool:
        """Its own direction is observed: past its threshold, it is broken."""
        return math.isfinite(self.sigma)

    @property
    def observable(self) -> bool:
        """Every direction it spans is observed: within its threshold, it holds."""
        return self.measured and self.seen


# The residuals a mate can have, in the order the files list them.
RESIDUALS = ("axis_distance_mm", "axis_angle_deg", "plane_offset_mm", "normal_angle_deg")


@dataclass(frozen=True)
class MateAsBuilt:
    """A CAD face mate as built (the keys of the mates stage: index_a, index_b, face_a, face_b,
    relation), its residuals and status."""

    index_a: int
    index_b: int
    face_a: int
    face_b: int
    relation: str
    status: str
    residuals: tuple[Residual, ...] = ()
    reason: str = ""

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> MateAsBuilt:
        """The mate of an ``as_built.csv`` row (``row``'s inverse; the residuals' standard
        deviations are not in the file: NaN)."""
        residuals = tuple(Residual(name, float(row[name]), float(row[f"{name}_threshold"]),
                                   math.nan) for name in RESIDUALS
                          if name in row and row[name] is not None
                          and math.isfinite(float(row[name])))
        return cls(int(row["index_a"]), int(row["index_b"]), int(row["face_a"]),
                   int(row["face_b"]), str(row["relation"]), str(row["status"]), residuals,
                   str(row.get("reason") or ""))

    def text(self) -> str:
        """The check in words: status, then each residual against its threshold."""
        said = "; ".join(f"{r.name} {r.value:.3g} (threshold {r.threshold:.3g})"
                         for r in self.residuals)
        return f"{self.status}" + (f": {said}" if said else f" ({self.reason})"
                                   if self.reason else "")

    def row(self) -> dict[str, Any]:
        """The ``as_built.csv`` row of the mate (residuals as ``<name>`` and their
        ``<name>_threshold`` columns)."""
        out: dict[str, Any] = {"index_a": self.index_a, "index_b": self.index_b,
                               "face_a": self.face_a, "face_b": self.face_b,
                               "relation": self.relation, "status": self.status,
                               "reason": self.reason}
        for r in self.residuals:
            out[r.name] = r.value
            out[f"{r.name}_threshold"] = r.threshold
        return out


@dataclass(frozen=True)
class Limits:
    """The tolerances a mate is held to, before the pose's uncertainty widens them."""

    axis_mm: float
    axis_deg: float
    plane_mm: float
    plane_deg: float
    sigmas: float = SIGMAS

    @classmethod
    def of(cls, tol: Tolerances = DEFAULT_TOLERANCES, sigmas: float = SIGMAS) -> Limits:
        return cls(tol.coaxial_mm, tol.coaxial_deg, tol.contact_mm, tol.mate_angle_deg, sigmas)


@dataclass(frozen=True)
class _Frame:
    """A mate's geometry in the assembly frame: direction (unit) and a point."""

    direction: FloatArray
    point: FloatArray
    extra: dict[str, float] = field(default_factory=dict)


def mate_as_built(row: Mapping[str, Any], parts: Mapping[int, PartAsBuilt],
                  design: Mapping[int, FloatArray], limits: Limits,
                  rest: Mapping[int, Rest] | None = None) -> MateAsBuilt:
    """One face mate of the design as built.

    Each part of the mate is also held against its partner where the rest of the assembly
    puts the partner (``rest``: per part, the consensus of the others, ``consensus.Rest``):
    a part moved off its place breaks its mate there even where the partner's own pose is too
    unsure to tell (a frame against a small pin), or too little of the partner is seen. The
    mate is broken where any of these readings is; its residuals are the reading that broke
    it most, or else the two registered parts'.

    Args:
        row: a face row of the assembly's mates table (index_a, index_b, face_a, face_b,
            relation, axis, origin: the axis or a's outward normal and a point, assembly frame).
        parts: each part as the scan shows it, by index.
        design: each part's designed pose (part -> assembly, mm), by index.
        rest: per part, where the rest of the assembly puts the others (None: no such reading).
    """
    a, b = int(row["index_a"]), int(row["index_b"])
    key = (a, b, int(row["face_a"]), int(row["face_b"]), str(row["relation"]))
    frame = _Frame(_unit(row["axis"]), np.asarray(row["origin"], dtype=np.float64))
    pair = (design[a], design[b])
    missing = [p for p in (parts.get(a), parts.get(b)) if p is None or p.problem]
    if any(p is not None and p.problem == "missing" for p in missing):
        gone = next(p for p in missing if p is not None and p.problem == "missing")
        return MateAsBuilt(*key, status=BROKEN, reason=f"part {gone.index}: missing")
    readings: list[tuple[str, tuple[Residual, ...]]] = []
    for one, other in ((a, b), (b, a)):
        mine = parts.get(one)
        if rest is None or one not in rest or mine is None or mine.problem:
            continue
        placed = rest[one].place(other)
        held = (mine, placed) if one == a else (placed, mine)
        readings.append((f"part {one} against part {other} where the rest of the assembly "
                         f"puts it", _residuals(key[4], frame, held, pair, limits)))
    broken = [(max(r.value / r.threshold for r in res if r.broken and r.measured), why, res)
              for why, res in readings if _status(res) == BROKEN]
    if missing:
        part = missing[0]
        if broken:
            _, why, res = max(broken, key=lambda item: item[0])
            return MateAsBuilt(*key, status=BROKEN, residuals=res, reason=why)
        why = "a part is not in the scan" if part is None else f"part {part.index}: {part.problem}"
        return MateAsBuilt(*key, status=NOT_INSPECTABLE, reason=why)
    pa, pb = parts[a], parts[b]
    assert pa.pose is not None and pb.pose is not None
    residuals = _residuals(key[4], frame, (pa, pb), pair, limits)
    if _status(residuals) != BROKEN and broken:
        _, why, res = max(broken, key=lambda item: item[0])
        return MateAsBuilt(*key, status=BROKEN, residuals=res, reason=why)
    return MateAsBuilt(*key, status=_status(residuals), residuals=residuals)


def _unit(v: Any) -> FloatArray:
    d = np.asarray(v, dtype=np.float64)
    unit: FloatArray = d / np.linalg.norm(d)
    return unit


def _status(residuals: Sequence[Residual]) -> str:
    if any(r.broken and r.measured for r in residuals):
        return BROKEN
    if not all(r.observable for r in residuals):
        return NOT_OBSERVABLE
    return HOLDS


def _residuals(relation: str, frame: _Frame, parts: tuple[PartAsBuilt, PartAsBuilt],
               design: tuple[FloatArray, FloatArray], limits: Limits) -> tuple[Residual, ...]:
    """The mate's residuals: a's pose relative to b's as built against as designed, read in
    the assembly frame at the mate (b's face stays where the design put it)."""
    (pa, pb), (da, db) = parts, design
    assert pa.pose is not None and pb.pose is not None
    # a's deviation from its place on b, in the assembly frame: D = Db Tb^-1 Ta Da^-1
    deviation = db @ np.linalg.inv(pb.pose) @ pa.pose @ np.linalg.inv(da)
    d, o = frame.direction, frame.point
    moved_d = deviation[:3, :3] @ d
    moved_o = deviation[:3, :3] @ o + deviation[:3, 3]
    angle = math.degrees(math.acos(float(np.clip(moved_d @ d, -1.0, 1.0))))
    offset = moved_o - o
    # the mate's point as each part carries it, and its directions (b's frame), in the world
    # where the poses' uncertainties live
    points = (_place(pa.pose @ np.linalg.inv(da), o), _place(pb.pose @ np.linalg.inv(db), o))
    to_world = pb.pose @ np.linalg.inv(db)
    world_d = to_world[:3, :3] @ d
    across = _across(world_d)
    # each residual is held to the sigma along its own direction (the offset across the axis,
    # the axis the tilt turns about), or the least sure across direction where it is nil; it
    # holds only where every direction across is observed
    turn_seen = all(math.isfinite(_sigma(parts, points, u, turn=True)) for u in across)
    tilt = _direction(to_world[:3, :3] @ np.cross(d, moved_d), across)
    turn_sigma = max(_sigma(parts, points, u, turn=True) for u in tilt)
    turn = Residual("axis_angle_deg" if relation == "concentric" else "normal_angle_deg", angle,
                    max(limits.axis_deg if relation == "concentric" else limits.plane_deg,
                        limits.sigmas * math.degrees(turn_sigma)),
                    math.degrees(turn_sigma), turn_seen)
    if relation == "concentric":
        across_offset = offset - (offset @ d) * d
        shift_sigma = max(_sigma(parts, points, u, turn=False)
                          for u in _direction(to_world[:3, :3] @ across_offset, across))
        shift_seen = all(math.isfinite(_sigma(parts, points, u, turn=False)) for u in across)
        return (Residual("axis_distance_mm", float(np.linalg.norm(across_offset)),
                         max(limits.axis_mm, limits.sigmas * shift_sigma), shift_sigma,
                         shift_seen), turn)
    shift_sigma = _sigma(parts, points, world_d, turn=False)
    return (Residual("plane_offset_mm", abs(float(offset @ d)),
                     max(limits.plane_mm, limits.sigmas * shift_sigma), shift_sigma), turn)


def _place(pose: FloatArray, point: FloatArray) -> FloatArray:
    placed: FloatArray = pose[:3, :3] @ point + pose[:3, 3]
    return placed


def _direction(v: FloatArray, fallback: tuple[FloatArray, ...]) -> tuple[FloatArray, ...]:
    """``v`` as a unit vector, or ``fallback`` where it is nil."""
    norm = float(np.linalg.norm(v))
    if norm < 1e-9:
        return fallback
    return (v / norm,)


def _across(d: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors across ``d``."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(d, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(d, u)


def _sigma(parts: tuple[PartAsBuilt, PartAsBuilt], points: tuple[FloatArray, FloatArray],
           direction: FloatArray, turn: bool) -> float:
    """Standard deviation of the relative motion of the two parts at the mate's point (as each
    part carries it) along ``direction`` (mm), or of their relative turn about it (radians);
    inf where a part's view does not constrain it."""
    total = 0.0
    for part, point in zip(parts, points, strict=True):
        u = part.uncertainty
        if u is None:
            return math.inf
        functional = np.concatenate([direction, np.zeros(3)]) if turn else \
            direction @ point_motion(point, u.centre)
        s = u.sigma_along(functional)
        if not math.isfinite(s):
            return math.inf
        total += s * s
    return math.sqrt(total)


def assembly_as_built(rows: Sequence[Mapping[str, Any]], parts: Mapping[int, PartAsBuilt],
                      design: Mapping[int, FloatArray], limits: Limits | None = None,
                      rest: Mapping[int, Rest] | None = None) -> list[MateAsBuilt]:
    """Every face mate (concentric, coincident) of the design as built (``mate_as_built``)."""
    chosen = limits or Limits.of()
    return [mate_as_built(r, parts, design, chosen, rest) for r in rows
            if r["level"] == "face" and r["relation"] in ("concentric", "coincident")]


def verdict(mates: Sequence[MateAsBuilt]) -> str:
    """An assembly's verdict: ``holds``, ``N mates broken`` or ``not inspectable``."""
    return verdict_of([m.status for m in mates])


def verdict_of(statuses: Sequence[str]) -> str:
    """The verdict of an assembly's mates from their statuses (the rule of every report, the
    export and ``mateqa inspect``)."""
    broken = sum(s == BROKEN for s in statuses)
    if broken:
        return f"{broken} mate{'s' if broken > 1 else ''} broken"
    if statuses and all(s == NOT_INSPECTABLE for s in statuses):
        return NOT_INSPECTABLE
    return HOLDS
