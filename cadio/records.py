"""Typed records that cross module borders: categories, relations, parts, geometry, frames.

Records holding arrays compare by identity (``eq=False``): element-wise ``==`` on arrays has no
single truth value, so compare their fields explicitly where equality matters.

Array fields state dtype, shape and unit. Records are frozen; geometry is in millimetres in the
part's own coordinates unless a field says otherwise. Timestamps are integer nanoseconds.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


class Category(enum.StrEnum):
    """The four part categories of the paper (TraceParts taxonomy), plus anything else."""

    BRAKES = "brakes-clutches-couplings"
    CASTERS = "casters-wheels-trolleys"
    FASTENERS = "fasteners"
    MOTION = "linear-rotary-motion"

    @classmethod
    def paper(cls) -> tuple[str, ...]:
        """The four category folder names used in the paper's tables."""
        return tuple(c.value for c in cls)


class Relation(enum.StrEnum):
    """The ten spatial relations, in the paper's order."""

    LEFT = "left"
    RIGHT = "right"
    ABOVE = "above"
    BELOW = "below"
    FRONT = "front"
    BEHIND = "behind"
    PARALLEL = "parallel"
    PERPENDICULAR = "perpendicular"
    CONCENTRIC = "concentric"
    COINCIDENT = "coincident"


DIRECTIONAL = (
    Relation.LEFT, Relation.RIGHT, Relation.ABOVE, Relation.BELOW, Relation.FRONT, Relation.BEHIND
)
# Contrasting pairs of the paper's rule (4): r(a, b) iff converse(r)(b, a).
CONVERSE = {
    Relation.LEFT: Relation.RIGHT, Relation.RIGHT: Relation.LEFT,
    Relation.ABOVE: Relation.BELOW, Relation.BELOW: Relation.ABOVE,
    Relation.FRONT: Relation.BEHIND, Relation.BEHIND: Relation.FRONT,
}
SYMMETRIC = (Relation.PARALLEL, Relation.PERPENDICULAR, Relation.CONCENTRIC, Relation.COINCIDENT)


# A runner-up group carrying at least this fraction of the winner's area makes the principal
# choice a tie (DESIGN.md: ties are flagged); the earliest group is then chosen, so the choice
# does not flip with rounding noise when the part moves. One rule for B-rep and fitted features.
TIE_FRACTION = 0.99


def principal_choice(areas: Sequence[float]) -> tuple[int | None, bool]:
    """Index of the principal group (the largest area; the earliest of a tie) and whether the
    choice is a tie (a runner-up within ``TIE_FRACTION`` of it); (None, False) without groups."""
    if not areas:
        return None, False
    best = max(areas)
    near = [i for i, a in enumerate(areas) if a >= TIE_FRACTION * best]
    return near[0], len(near) > 1


def dominant_choice(planes: Sequence[PlaneGroup], angle_deg: float,
                    ratio: float) -> tuple[FloatArray | None, float]:
    """A part's dominant plane direction, from its planar face groups (DESIGN.md, "Relations").

    Groups whose normals lie within ``angle_deg`` of a direction's first group (sign ignored,
    greedy in group order, so the result does not change when the part moves) are one
    direction; it carries their total area. The direction carrying the largest area is dominant
    when that is at least ``ratio`` times the runner-up's.

    Returns:
        (unit normal (3,) with the canonical sign, or None when no direction is dominant, and
        the runner-up's area over the largest's, in [0, 1]: 0 with one direction or none).
    """
    seeds: list[FloatArray] = []
    sums: list[FloatArray] = []
    areas: list[float] = []
    cos = math.cos(math.radians(angle_deg))
    for g in planes:
        for k, seed in enumerate(seeds):
            dot = float(np.dot(seed, g.normal))
            if abs(dot) >= cos - 1e-9:  # rounding of angles computed at the tolerance
                sums[k] = sums[k] + g.area * math.copysign(1.0, dot) * g.normal
                areas[k] += g.area
                break
        else:
            seeds.append(g.normal)
            sums.append(g.area * g.normal)
            areas.append(g.area)
    if not areas or max(areas) <= 0.0:
        return None, 0.0
    order = sorted(range(len(areas)), key=lambda k: -areas[k])
    runner_up = areas[order[1]] / areas[order[0]] if len(order) > 1 else 0.0
    if runner_up * ratio > 1.0 + 1e-9:  # values at the ratio count as dominant
        return None, runner_up
    return _canonical(sums[order[0]]), runner_up


def _vec(values: Any) -> FloatArray:
    return np.asarray(values, dtype=np.float64).reshape(3)


def apply_pose(pose: FloatArray, points: FloatArray) -> FloatArray:
    """Apply a 4x4 rigid transform to points (n, 3) (or one point (3,)); same shape back."""
    pts = np.asarray(points, dtype=np.float64)
    return pts @ pose[:3, :3].T + pose[:3, 3]


@dataclass(frozen=True, eq=False)
class PlaneGroup:
    """Planar faces sharing one normal direction (sign ignored).

    normal: (3,) float64, unit, canonical sign (first non-zero component positive).
    offsets: per face, signed distance n . p of its plane from the origin, mm.
    outward: per face, +1 if the face's outward normal equals ``normal``, else -1.
    """

    normal: FloatArray
    area: float
    face_ids: tuple[int, ...]
    face_areas: tuple[float, ...]
    offsets: tuple[float, ...]
    outward: tuple[int, ...]


@dataclass(frozen=True, eq=False)
class AxisGroup:
    """Cylindrical or conical faces sharing one axis line.

    direction: (3,) float64, unit, canonical sign. point: (3,) float64 mm, the point of the axis
    line closest to the origin. radii: per face, mm (for a cone, the reference radius).
    """

    kind: str  # "cylinder" or "cone"
    direction: FloatArray
    point: FloatArray
    area: float
    face_ids: tuple[int, ...]
    radii: tuple[float, ...]


@dataclass(frozen=True, eq=False)
class Features:
    """Geometric features of one part, from exact B-rep or from primitives fitted to points.

    centroid: (3,) mm (volume centroid). bbox_min, bbox_max: (3,) mm, axis-aligned.
    principal_plane: (3,) unit normal direction carrying the largest planar area, or None.
    principal_axis: the cylindrical axis group carrying the largest area, or None.
    *_tie: True when the runner-up carries (within 1%) the same area, so the choice is arbitrary.
    dominant_plane: (3,) unit normal of the dominant plane direction (``dominant_choice``:
        normals within ``Tolerances.dominant_group_deg`` as one direction, at least
        ``dominant_area_ratio`` times the runner-up's area), or None: parallel and
        perpendicular are decided on it. dominant_runner_up: the runner-up direction's area
        over the largest's, [0, 1] (0 with one direction or none).
    """

    centroid: FloatArray
    bbox_min: FloatArray
    bbox_max: FloatArray
    volume: float
    area: float
    planes: tuple[PlaneGroup, ...]
    axes: tuple[AxisGroup, ...]
    principal_plane: FloatArray | None
    principal_axis: AxisGroup | None
    principal_plane_tie: bool = False
    principal_axis_tie: bool = False
    n_faces: int = 0
    n_freeform_recognised: int = 0
    dominant_plane: FloatArray | None = None
    dominant_runner_up: float = 0.0

    def principal_axis_index(self) -> int:
        """Position of ``principal_axis`` in ``axes`` (by identity: records hold arrays)."""
        return next(i for i, a in enumerate(self.axes) if a is self.principal_axis)

    def transformed(self, pose: FloatArray) -> Features:
        """These features after the rigid motion ``pose`` (4, 4) float64 (mm)."""
        rot = np.asarray(pose[:3, :3], dtype=np.float64)
        corners = np.array(
            [[x, y, z] for x in (self.bbox_min[0], self.bbox_max[0])
             for y in (self.bbox_min[1], self.bbox_max[1])
             for z in (self.bbox_min[2], self.bbox_max[2])]
        )
        moved = apply_pose(pose, corners)
        planes = tuple(_move_plane(g, pose) for g in self.planes)
        axes = tuple(_move_axis(a, pose) for a in self.axes)
        principal_axis = None
        if self.principal_axis is not None:
            principal_axis = axes[self.principal_axis_index()]
        principal_plane = None
        if self.principal_plane is not None:
            principal_plane = _canonical(rot @ self.principal_plane)
        dominant = None if self.dominant_plane is None else _canonical(rot @ self.dominant_plane)
        return replace(
            self,
            centroid=apply_pose(pose, self.centroid),
            bbox_min=moved.min(axis=0),
            bbox_max=moved.max(axis=0),
            planes=planes,
            axes=axes,
            principal_plane=principal_plane,
            principal_axis=principal_axis,
            dominant_plane=dominant,
        )

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (lists of floats); ``from_dict`` inverts it exactly."""
        def plane(g: PlaneGroup) -> dict[str, Any]:
            return {"normal": g.normal.tolist(), "area": g.area, "face_ids": list(g.face_ids),
                    "face_areas": list(g.face_areas), "offsets": list(g.offsets),
                    "outward": list(g.outward)}

        def axis(a: AxisGroup) -> dict[str, Any]:
            return {"kind": a.kind, "direction": a.direction.tolist(), "point": a.point.tolist(),
                    "area": a.area, "face_ids": list(a.face_ids), "radii": list(a.radii)}

        return {
            "centroid": self.centroid.tolist(),
            "bbox_min": self.bbox_min.tolist(),
            "bbox_max": self.bbox_max.tolist(),
            "volume": self.volume,
            "area": self.area,
            "planes": [plane(g) for g in self.planes],
            "axes": [axis(a) for a in self.axes],
            "principal_plane": None if self.principal_plane is None
            else self.principal_plane.tolist(),
            "principal_axis": None if self.principal_axis is None
            else self.principal_axis_index(),
            "principal_plane_tie": self.principal_plane_tie,
            "principal_axis_tie": self.principal_axis_tie,
            "n_faces": self.n_faces,
            "n_freeform_recognised": self.n_freeform_recognised,
            "dominant_plane": None if self.dominant_plane is None
            else self.dominant_plane.tolist(),
            "dominant_runner_up": self.dominant_runner_up,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Features:
        """Rebuild features written by ``to_dict``."""
        planes = tuple(
            PlaneGroup(_vec(g["normal"]), float(g["area"]), tuple(g["face_ids"]),
                       tuple(g["face_areas"]), tuple(g["offsets"]), tuple(g["outward"]))
            for g in d["planes"]
        )
        axes = tuple(
            AxisGroup(a["kind"], _vec(a["direction"]), _vec(a["point"]), float(a["area"]),
                      tuple(a["face_ids"]), tuple(a["radii"]))
            for a in d["axes"]
        )
        pa = d.get("principal_axis")
        pp = d.get("principal_plane")
        return cls(
            centroid=_vec(d["centroid"]), bbox_min=_vec(d["bbox_min"]),
            bbox_max=_vec(d["bbox_max"]), volume=float(d["volume"]), area=float(d["area"]),
            planes=planes, axes=axes,
            principal_plane=None if pp is None else _vec(pp),
            principal_axis=None if pa is None else axes[int(pa)],
            principal_plane_tie=bool(d.get("principal_plane_tie", False)),
            principal_axis_tie=bool(d.get("principal_axis_tie", False)),
            n_faces=int(d.get("n_faces", 0)),
            n_freeform_recognised=int(d.get("n_freeform_recognised", 0)),
            dominant_plane=None if d.get("dominant_plane") is None
            else _vec(d["dominant_plane"]),
            dominant_runner_up=float(d.get("dominant_runner_up", 0.0)),
        )


def _canonical(direction: FloatArray) -> FloatArray:
    """Unit vector with the sign fixed so that its first clearly non-zero component is > 0."""
    v = np.asarray(direction, dtype=np.float64)
    v = v / np.linalg.norm(v)
    for c in v:
        if abs(c) > 1e-9:
            return v if c > 0 else -v
    return v


def canonical_direction(direction: Any) -> FloatArray:
    """Public form of the sign convention used for plane normals and axis directions."""
    return _canonical(np.asarray(direction, dtype=np.float64))


def perpendicular_pair(direction: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors perpendicular to the unit ``direction`` (3,) and to each other."""
    helper = np.eye(3)[int(np.argmin(np.abs(direction)))]
    e1 = np.cross(direction, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(direction, e1)


def _move_plane(g: PlaneGroup, pose: FloatArray) -> PlaneGroup:
    rot, t = pose[:3, :3], pose[:3, 3]
    n_raw = rot @ g.normal
    n = _canonical(n_raw)
    sign = 1.0 if np.dot(n, n_raw) > 0 else -1.0
    # plane n_raw . x = d + n_raw . t after the motion; re-express along the canonical normal.
    shift = float(np.dot(n_raw, t))
    offsets = tuple(sign * (o + shift) for o in g.offsets)
    outward = tuple(int(sign) * o for o in g.outward)
    return replace(g, normal=n, offsets=offsets, outward=outward)


def _move_axis(a: AxisGroup, pose: FloatArray) -> AxisGroup:
    d = _canonical(pose[:3, :3] @ a.direction)
    p = apply_pose(pose, a.point)
    p = p - np.dot(p, d) * d  # closest point of the line to the origin
    return replace(a, direction=d, point=p)


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh. vertices: (n, 3) float64 mm; triangles: (m, 3) int64, outward CCW.

    missing_faces: B-rep faces the mesher could not triangulate (the mesh then has holes).
    """

    vertices: FloatArray
    triangles: npt.NDArray[np.int64]
    missing_faces: int = 0


@dataclass(frozen=True, eq=False)
class VoxelGrid:
    """Solid occupancy of a part on a cubic n^3 grid.

    occupancy: (n, n, n) bool, indexed [i, j, k] along part x, y, z.
    grid_to_part: (4, 4) float64: maps homogeneous (i, j, k, 1) to the centre of voxel (i, j, k)
    in part coordinates (mm). The grid is a cube centred on the part's bounding-box centre whose
    side is the largest bbox extent times (1 + margin), so shapes are never stretched.
    """

    occupancy: npt.NDArray[np.bool_]
    grid_to_part: FloatArray

    @property
    def n(self) -> int:
        return int(self.occupancy.shape[0])

    @property
    def voxel_size(self) -> float:
        """Edge of one voxel, mm."""
        return float(self.grid_to_part[0, 0])


@dataclass(frozen=True, eq=False)
class SolidInfo:
    """One solid read from a STEP file, before geometry processing.

    placement: (4, 4) float64, the solid's location in the file's (assembly) frame, mm.
    colour: sRGB hex "#rrggbb", or "" when the file gives none.
    """

    index: int
    name: str
    colour: str
    placement: FloatArray
    path_in_assembly: str = ""


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole camera (OpenCV convention: x right, y down, z forward), pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def matrix(self) -> FloatArray:
        """The 3x3 intrinsic matrix K."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=float)


@dataclass(frozen=True, eq=False)
class RgbdFrame:
    """One RGB-D view.

    colour: (h, w, 3) uint8 sRGB. depth: (h, w) float32 metres, 0 or NaN where missing.
    instance: (h, w) int32 instance ids (0 = background), or None when the source has none.
    world_to_camera: (4, 4) float64, metres (OpenCV camera frame).
    timestamp_ns: integer nanoseconds.
    """

    timestamp_ns: int
    intrinsics: CameraIntrinsics
    colour: npt.NDArray[np.uint8]
    depth: npt.NDArray[np.float32]
    world_to_camera: FloatArray
    instance: npt.NDArray[np.int32] | None = None
    meta: dict[str, Any] = field(default_factory=dict)
