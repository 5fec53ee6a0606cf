"""Synthetic examples for tests, smoke runs and benchmarks: completion solids, relation pairs.

Completion: each solid (a box or cylinder) is voxelized at n_out; each view observes the surface
voxels that a camera looking along one grid axis sees first, at n_in (a voxel of the coarse grid
is occupied when any of its fine voxels is). View 0 looks along +y, as the contract's first
camera does; later views look from the sides, behind, above and below. Depth images follow the
contract.

Relations (``relation_pairs``): pairs of boxes, plates and cylinders placed so that chosen
relations hold, labelled from the placement by simple rules.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from models.data import Example

if TYPE_CHECKING:
    from models.relations_train import RelationData

# (axis, reversed): the camera looks along +axis when not reversed. View 0 looks along +y.
VIEW_DIRECTIONS = ((1, False), (0, False), (0, True), (1, True), (2, True), (2, False))

BoolGrid = npt.NDArray[np.bool_]


def box(n: int, centre: npt.ArrayLike, half: npt.ArrayLike) -> BoolGrid:
    """Voxels of an axis-aligned box, centre and half sizes in voxels: (n, n, n) bool."""
    c = (np.arange(n) + 0.5)[:, None]
    inside = np.abs(c - np.asarray(centre, dtype=float)) <= np.asarray(half, dtype=float)
    return inside[:, 0, None, None] & inside[None, :, 1, None] & inside[None, None, :, 2]


def cylinder(n: int, centre: npt.ArrayLike, radius: float, half_height: float) -> BoolGrid:
    """Voxels of a cylinder with its axis along z: (n, n, n) bool."""
    x, y, z = np.asarray(centre, dtype=float)
    c = np.arange(n) + 0.5
    disc = (c[:, None] - x) ** 2 + (c[None, :] - y) ** 2 <= radius**2
    return disc[:, :, None] & (np.abs(c - z) <= half_height)[None, None, :]


def observe(solid: BoolGrid, n_in: int, view: int) -> BoolGrid:
    """The (2, n_in^3) states a camera looking along view ``view``'s axis gives of ``solid``:
    the coarse voxels it sees first (surface) and those its rays cross before (free)."""
    f = solid.shape[0] // n_in
    coarse = solid.reshape(n_in, f, n_in, f, n_in, f).any(axis=(1, 3, 5))
    axis, rev = VIEW_DIRECTIONS[view % len(VIEW_DIRECTIONS)]
    grid = np.flip(coarse, axis) if rev else coarse
    hits = np.cumsum(grid, axis=axis)
    first, free = grid & (hits == 1), hits == 0
    if rev:
        first, free = np.flip(first, axis), np.flip(free, axis)
    return np.stack([first, free])


def depth_image(observed: BoolGrid) -> npt.NDArray[np.float32]:
    """The contract's (2, 2n, 2n) depth view of one view's observed grid, indexed (x, z)."""
    n = observed.shape[0]
    seen = observed.any(axis=1)  # (x, z)
    dist = np.where(seen, (observed.argmax(axis=1) + 0.5) / n, 1.0)
    image = np.stack([dist, seen]).astype(np.float32)
    return image.repeat(2, axis=1).repeat(2, axis=2)


def example(solid: BoolGrid, n_in: int, n_views: int, meta: dict[str, object]) -> Example:
    """An example of ``solid`` seen from views 0..n_views-1."""
    inputs = np.stack([observe(solid, n_in, v) for v in range(n_views)])
    depth = np.stack([depth_image(obs[0]) for obs in inputs])
    return Example(inputs, solid, depth, meta)


def synthetic_examples(count: int, n_in: int = 32, n_out: int = 64, n_views: int = 3,
                       seed: int = 0) -> list[Example]:
    """``count`` random boxes and cylinders (alternating), each seen from ``n_views`` views."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        centre = n_out / 2 + rng.uniform(-0.1, 0.1, 3) * n_out
        if i % 2 == 0:
            solid = box(n_out, centre, rng.uniform(0.12, 0.35, 3) * n_out)
            kind = "box"
        else:
            r, h = rng.uniform(0.12, 0.35) * n_out, rng.uniform(0.15, 0.35) * n_out
            solid = cylinder(n_out, centre, r, h)
            kind = "cylinder"
        out.append(example(solid, n_in, n_views, {"part_id": f"{kind}-{i}", "category": kind}))
    return out


# Relation pairs: directions of a's centre seen from b's, in Relation order (left, right, above,
# below, front, behind) in the observer's frame (x right, y behind, z up).
_DIRECTIONS = np.array([[-1, 0, 0], [1, 0, 0], [0, 0, 1], [0, 0, -1], [0, -1, 0], [0, 1, 0]],
                       dtype=float)
_CONE_DEG = 15.0  # a directional relation holds within this angle of its axis
_LINE_DEG = 10.0  # parallel within this angle; perpendicular within it of 90 degrees
_KINDS = ("box", "plate", "cylinder")
# Scenarios and their odds: free placement, then the four that make symmetric relations hold.
_SCENARIOS = ("free", "parallel", "perpendicular", "concentric", "coincident")
_SCENARIO_P = (0.4, 0.15, 0.15, 0.15, 0.15)


def _unit(v: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return v / np.linalg.norm(v)


def _tilt(v: npt.NDArray[np.float64], max_deg: float,
          rng: np.random.Generator) -> npt.NDArray[np.float64]:
    """``v`` turned by up to ``max_deg`` degrees towards a random perpendicular direction."""
    perp = _unit(np.cross(v, rng.standard_normal(3)))
    angle = np.radians(rng.uniform(0, max_deg))
    return np.cos(angle) * v + np.sin(angle) * perp


def _axis(rng: np.random.Generator) -> npt.NDArray[np.float64]:
    """A part's main axis: mostly a frame axis slightly tilted, sometimes any direction."""
    if rng.random() < 0.75:
        return _tilt(np.eye(3)[rng.integers(3)], 4.0, rng)
    return _unit(rng.standard_normal(3))


def _part_points(kind: str, axis: npt.NDArray[np.float64], centre: npt.NDArray[np.float64],
                 half: npt.NDArray[np.float64], n: int,
                 rng: np.random.Generator) -> npt.NDArray[np.float64]:
    """``n`` points filling a box, plate (thin box, normal ``axis``) or cylinder (``axis``)."""
    e1 = _unit(np.cross(axis, rng.standard_normal(3)))
    frame = np.stack([e1, np.cross(axis, e1), axis], 1)  # columns: local x, y, z
    if kind == "cylinder":
        rad, theta = half[0] * np.sqrt(rng.random(n)), rng.uniform(0, 2 * np.pi, n)
        local = np.stack([rad * np.cos(theta), rad * np.sin(theta),
                          half[2] * rng.uniform(-1, 1, n)], 1)
    else:
        local = rng.uniform(-1, 1, (n, 3)) * half
    return np.asarray(centre + local @ frame.T)


def _half_sizes(kind: str, rng: np.random.Generator) -> npt.NDArray[np.float64]:
    if kind == "plate":
        return np.array([*rng.uniform(0.4, 0.8, 2), rng.uniform(0.03, 0.06)])
    if kind == "cylinder":
        r = rng.uniform(0.15, 0.4)
        return np.array([r, r, rng.uniform(0.3, 0.7)])
    return rng.uniform(0.2, 0.6, 3)


def _offset(rng: np.random.Generator) -> npt.NDArray[np.float64]:
    """a's centre minus b's: mostly near an axis of the observer (some outside the cone)."""
    if rng.random() < 0.6:
        direction = _tilt(_DIRECTIONS[rng.integers(6)], 25.0, rng)
    else:
        direction = _unit(rng.standard_normal(3))
    return direction * rng.uniform(1.2, 2.5)


def _line_deg(u: npt.NDArray[np.float64], v: npt.NDArray[np.float64]) -> float:
    return float(np.degrees(np.arccos(np.clip(abs(float(u @ v)), 0.0, 1.0))))


def _relation_labels(kinds: tuple[str, str], axes: tuple[npt.NDArray[np.float64], ...],
                     halves: tuple[npt.NDArray[np.float64], ...],
                     offset: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
    """The ten relations of (a, b) from the placement (``offset`` = a's centre - b's)."""
    cos = _DIRECTIONS @ _unit(offset)
    labels = np.zeros(10, dtype=bool)
    labels[:6] = cos >= np.cos(np.radians(_CONE_DEG))
    angle = _line_deg(axes[0], axes[1])
    if kinds == ("plate", "plate"):
        labels[6] = angle <= _LINE_DEG
        labels[7] = angle >= 90 - _LINE_DEG
        gap = abs(float(offset @ axes[0])) - halves[0][2] - halves[1][2]
        labels[9] = bool(labels[6] and abs(gap) <= 0.02)  # face to face: coplanar faces
    if kinds == ("cylinder", "cylinder"):
        off_axis = offset - (offset @ axes[1]) * axes[1]
        labels[8] = angle <= _LINE_DEG and float(np.linalg.norm(off_axis)) <= 0.05
    return labels


def _relation_pair(n_points: int, rng: np.random.Generator
                   ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_]]:
    """One pair's (2, n, 3) points (b's centre at the origin, unit-ish sizes) and labels."""
    scenario = _SCENARIOS[rng.choice(len(_SCENARIOS), p=_SCENARIO_P)]
    axis_a = _axis(rng)
    if scenario == "free":
        kinds = (str(rng.choice(_KINDS)), str(rng.choice(_KINDS)))
        axis_b = _axis(rng)
    else:
        kinds = ("cylinder",) * 2 if scenario == "concentric" else ("plate",) * 2
        turn = _unit(np.cross(axis_a, rng.standard_normal(3)))
        axis_b = _tilt(turn if scenario == "perpendicular" else axis_a,
                       5.0 if scenario in ("parallel", "perpendicular") else 0.0, rng)
    halves = (_half_sizes(kinds[0], rng), _half_sizes(kinds[1], rng))
    offset = _offset(rng)
    if scenario in ("concentric", "coincident"):
        sign = rng.choice([-1.0, 1.0])
        along = halves[0][2] + halves[1][2] + (rng.uniform(0, 0.5) if scenario == "concentric"
                                               else 0.0)
        offset = sign * along * axis_a
        if scenario == "coincident":  # slide within the shared plane
            offset = offset + rng.uniform(-0.3, 0.3) * _unit(np.cross(axis_a, rng.normal(size=3)))
    pts = np.stack([_part_points(kinds[0], axis_a, offset, halves[0], n_points, rng),
                    _part_points(kinds[1], axis_b, np.zeros(3), halves[1], n_points, rng)])
    return pts, _relation_labels(kinds, (axis_a, axis_b), halves, offset)


def relation_pairs(count: int, n_points: int = 600, seed: int = 0) -> RelationData:
    """``count`` labelled pairs of boxes, plates and cylinders in the observer's frame.

    Each pair is a free placement or one made for parallel, perpendicular, concentric or
    coincident (face-to-face plates) to hold; labels follow from the placement: directional
    when a's centre seen from b's is within 15 degrees of an axis, parallel/perpendicular from
    plate normals (10 degrees), concentric from cylinder axes. Each pair is then scaled by a
    random factor in [0.01, 10] and shifted, so the units are arbitrary; ``mm`` says what a
    unit is (a unit before scaling is 30 mm of parts).
    """
    from models.relations_train import RelationData  # torch only for callers who want pairs

    rng = np.random.default_rng(seed)
    points = np.empty((count, 2, n_points, 3), dtype=np.float32)
    labels = np.empty((count, 10), dtype=bool)
    mm = np.empty(count)
    for i in range(count):
        pts, labels[i] = _relation_pair(n_points, rng)
        scale = 10 ** rng.uniform(-2, 1)
        points[i] = (pts + rng.uniform(-2, 2, 3)) * scale
        mm[i] = 30.0 / scale  # a unit of the pair before scaling is 30 mm of parts
    return RelationData(points, labels, mm)
