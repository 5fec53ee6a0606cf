"""A part's symmetries, from its CAD surface, and pose errors that respect them.

A revolved part (a washer, a shaft) looks the same turned about its axis by any angle; a ball
turned about any axis through its centre; a hex nut by a sixth of a turn, and flipped end for
end; a plate by half a turn about each of its axes. A registration that lands on a symmetric
copy of the true pose is right, so a pose error is the least over the part's symmetries (as BOP
counts it). ``symmetry_of`` finds them on the part's surface samples: for each principal axis,
the largest n-fold turn that maps the surface onto itself (continuous when turns by angles no
n-fold would allow also do), and whether half a turn about an axis across it does (a flip);
a part revolved about two axes is a ball.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from pykdtree.kdtree import KDTree

from cadio.records import FloatArray

# Orders tried about an axis, largest first: a bolt pattern's or a gear's teeth past 24 read as
# continuous only if the odd angles pass too.
ORDERS = (72, 60, 48, 36, 32, 24, 20, 18, 16, 12, 10, 9, 8, 7, 6, 5, 4, 3, 2)
# Turns that no order above allows: a surface they map onto itself is revolved.
ODD_DEGREES = (7.3, 41.9, 97.1)


@dataclass(frozen=True)
class Symmetry:
    """A part's symmetry group about its centroid (its own frame, mm).

    axis: (3,) unit, the axis of the turns (None: no turn maps the part onto itself); order:
    n of the n-fold turns about it (0: continuous, a revolved part); flip: (3,) unit, an axis
    across ``axis`` half a turn about which maps the part onto itself (None: none);
    spherical: every turn about ``centre`` maps it onto itself (a ball: revolved about two
    axes), where ``axis`` and ``flip`` are two of them.
    """

    centre: tuple[float, float, float]
    axis: tuple[float, float, float] | None = None
    order: int = 1
    flip: tuple[float, float, float] | None = None
    # The turn's centre on its axis and the flip's centre, where the self-fit moved them off
    # the centroid (a part symmetric but for small features has its centroid off the axis).
    axis_point: tuple[float, float, float] | None = None
    flip_point: tuple[float, float, float] | None = None
    spherical: bool = False

    @property
    def continuous(self) -> bool:
        return self.axis is not None and self.order == 0

    def to_dict(self) -> dict[str, object]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> Symmetry:
        def vec(v: object) -> tuple[float, float, float] | None:
            if v is None:
                return None
            x, y, z = (float(c) for c in v)  # type: ignore[attr-defined]
            return x, y, z
        centre = vec(data["centre"])
        assert centre is not None
        return cls(centre, vec(data.get("axis")), int(data.get("order", 1)),  # type: ignore[call-overload]
                   vec(data.get("flip")), vec(data.get("axis_point")),
                   vec(data.get("flip_point")), bool(data.get("spherical", False)))

    def transforms(self) -> list[FloatArray]:
        """The group's elements as (4, 4) part-frame motions (a continuous turn sampled every
        degree, a ball's turns about its axis and its flip only; ``pose_error`` reads them
        exactly)."""
        centre = np.array(self.centre)
        out = [np.eye(4)]
        if self.axis is not None:
            n = 360 if self.order == 0 else self.order
            at = np.array(self.axis_point or self.centre)
            out = [_about(_turn(np.array(self.axis), 2 * math.pi * k / n), at)
                   for k in range(n)]
        if self.flip is not None:
            half = _about(_turn(np.array(self.flip), math.pi),
                          np.array(self.flip_point or centre))
            out += [half @ t for t in out]
        return out


def _about(rot: FloatArray, point: FloatArray) -> FloatArray:
    """(4, 4): the rotation about an axis through ``point``."""
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = point - rot @ point
    return m


def _turn(axis: FloatArray, angle: float) -> FloatArray:
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    rot: FloatArray = np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx
    return rot


def symmetry_of(samples: FloatArray, tolerance_mm: float | None = None) -> Symmetry:
    """The symmetries of a surface given by its samples (n, 3) mm, part frame.

    Args:
        tolerance_mm: how far a turned sample may lie from the nearest sample for the turn to
            map the surface onto itself (mean distance); default 1.5 times the samples'
            spacing.
    """
    pts = np.ascontiguousarray(samples, dtype=np.float64)
    centre = pts.mean(axis=0)
    tree = KDTree(pts)  # scipy's answers, in a third of its time (the registration's tree)
    spacing = float(np.median(tree.query(pts[:2000], k=2)[0][:, 1]))
    tol = tolerance_mm if tolerance_mm is not None else 1.5 * spacing
    _, vectors = np.linalg.eigh((pts - centre).T @ (pts - centre))

    def maps(rot: FloatArray) -> bool:
        moved = np.ascontiguousarray((pts[::7] - centre) @ rot.T + centre)
        return float(tree.query(moved)[0].mean()) <= tol

    best: tuple[FloatArray, int] | None = None
    for axis in vectors.T:
        order = next((n for n in ORDERS if maps(_turn(axis, 2 * math.pi / n))), 1)
        if order > 1 and all(maps(_turn(axis, math.radians(d))) for d in ODD_DEGREES):
            order = 0
        if order != 1 and (best is None or _rank(order) > _rank(best[1])):
            best = (axis, order)
    c = (float(centre[0]), float(centre[1]), float(centre[2]))
    if best is None:
        return Symmetry(c)
    axis, order = best
    flip = next((v for v in _across(axis, vectors) if maps(_turn(v, math.pi))), None)
    # revolved about a second axis too: a ball, which any turn about its centre maps onto itself
    spherical = order == 0 and any(
        maps(_turn(v, 2 * math.pi / ORDERS[0])) and all(
            maps(_turn(v, math.radians(d))) for d in ODD_DEGREES)
        for v in vectors.T if abs(float(v @ axis)) < 0.9)
    step = 2 * math.pi / (order or 12)
    axis, axis_point = _self_fit(pts, _about(_turn(axis, step), centre), step)
    flip_point = None
    if flip is not None:
        flip, flip_point = _self_fit(pts, _about(_turn(flip, math.pi), centre), math.pi)
    return Symmetry(c, _tuple(axis), order, None if flip is None else _tuple(flip),
                    _tuple_point(axis_point), _tuple_point(flip_point), spherical)


def _self_fit(pts: FloatArray, guess: FloatArray, angle: float
              ) -> tuple[FloatArray, FloatArray]:
    """The exact self-map near ``guess`` (point-to-point ICP of the samples onto themselves),
    as its axis and a point on it: a part symmetric but for small features is mapped about
    its true axis, not about its centroid."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    spacing = float(np.median(KDTree(pts).query(pts[:500], k=2)[0][:, 1]))
    fit = o3d.pipelines.registration.registration_icp(
        cloud, cloud, 3 * spacing, guess,
        o3d.pipelines.registration.TransformationEstimationPointToPoint())
    m = np.asarray(fit.transformation)
    rot, t = m[:3, :3], m[:3, 3]
    w, v = np.linalg.eig(rot)
    axis = np.real(v[:, int(np.argmin(np.abs(w - 1)))])
    # a point on the axis: the least-squares solution of (I - R) x = t, across the axis
    point = np.linalg.lstsq(np.eye(3) - rot, t, rcond=None)[0]
    point -= axis * float(axis @ (point - pts.mean(axis=0)))
    unit: FloatArray = np.asarray(axis / np.linalg.norm(axis), dtype=np.float64)
    return unit, np.asarray(point, dtype=np.float64)


def _tuple_point(v: FloatArray | None) -> tuple[float, float, float] | None:
    return None if v is None else (float(v[0]), float(v[1]), float(v[2]))


def _rank(order: int) -> int:
    return 10_000 if order == 0 else order


def _across(axis: FloatArray, vectors: FloatArray) -> list[FloatArray]:
    """Axes across ``axis``: the other principal axes, and between them every 15 degrees (a
    flip of a hex nut lies across a flat or a corner)."""
    others = [v for v in vectors.T if abs(float(v @ axis)) < 0.9]
    if len(others) < 2:
        return others
    a, b = others[0], others[1]
    return [math.cos(t) * a + math.sin(t) * b for t in np.radians(np.arange(0, 180, 15))]


def _tuple(v: FloatArray) -> tuple[float, float, float]:
    u = v / np.linalg.norm(v)
    return float(u[0]), float(u[1]), float(u[2])


def pose_error(estimate: FloatArray, truth: FloatArray, symmetry: Symmetry
               ) -> tuple[float, float]:
    """(mm, degrees) between two poses of a part (part -> world, (4, 4) mm), the least over
    its symmetries: of the symmetric copies of ``estimate``, the one whose rotation is nearest
    ``truth``'s, and the distance its centroid lies from the truth's. For a revolved part the
    turn about its axis is free: the angle is the one between the axis's two images (or its
    flip's), the distance a point on the axis's; a ball's every turn is: the angle is nil, the
    distance its centre's."""
    if symmetry.spherical:
        return _distance(estimate, truth, np.array(symmetry.centre)), 0.0
    if symmetry.continuous:
        axis = np.array(symmetry.axis)
        point = np.array(symmetry.axis_point or symmetry.centre)
        cos = float(np.clip((estimate[:3, :3] @ axis) @ (truth[:3, :3] @ axis), -1, 1))
        angle = math.degrees(math.acos(abs(cos) if symmetry.flip is not None else cos))
        return _distance(estimate, truth, point), angle
    centre = np.array(symmetry.centre)
    best = (math.inf, math.inf)
    for s in symmetry.transforms():
        copy = estimate @ s
        rel = copy[:3, :3] @ truth[:3, :3].T
        angle = math.degrees(math.acos(float(np.clip((np.trace(rel) - 1) / 2, -1, 1))))
        if angle < best[1]:
            best = (_distance(copy, truth, centre), angle)
    return best


def _distance(a: FloatArray, b: FloatArray, point: FloatArray) -> float:
    return float(np.linalg.norm((a[:3, :3] @ point + a[:3, 3]) - (b[:3, :3] @ point + b[:3, 3])))
