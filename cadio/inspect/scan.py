"""The points an inspection reads: a capture's depth back-projected, the table taken away.

An inspection capture is a recording: depth images with their cameras (and, where a simulation
wrote them, instance ids: the paper's segmented clouds), never the parts' names or poses. Its
views are back-projected into one cloud in the world frame, millimetres; the support the parts
stand on (the largest plane facing up, by the gravity the recording gives) is taken away, as
inspection software does before it fits anything. Where the frames carry instance ids each
instance's points are kept apart (``segments``); a real recording has none, and registration
decides which points are which part.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from cadio.camera.noise import D435, NoiseConfig
from cadio.capture.pointcloud import backproject
from cadio.inspect.surface import MM_PER_M, Camera, camera_of, voxel_down
from cadio.records import FloatArray, RgbdFrame

IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class ScanConfig:
    """How a capture becomes the inspection's points. Lengths mm."""

    voxel_mm: float = 0.7  # one point per voxel of this side: below the sensor's spacing
    plane_mm: float = 3.0  # points this near the support plane are the support's
    plane_normal_deg: float = 15.0  # the support faces up within this (gravity: -Z)
    plane_iterations: int = 300
    # The camera whose depth the points are: each point's standard deviation follows from its
    # distance to the camera that saw it (``Scan.sigma``: a view from 0.3 m weighs about ten
    # times one from 0.6 m in a fit).
    sensor: NoiseConfig = D435


@dataclass(frozen=True, eq=False)
class Scan:
    """One view's or several views' points, world mm, with their cameras.

    points: (n, 3); view: (n,) the view each came from; segments: instance id -> the indices
    of its points (only where the frames carried instance ids); support: the plane removed
    (unit normal, offset: n . x = offset), or None; labels: per camera (h, w) the instance id
    of each pixel (0: none or the support), only where the frames carried ids; sigma: (n,) the
    sensor's standard deviation of each point's depth (mm), None where unknown (every point
    alike).
    """

    points: FloatArray
    view: IntArray
    cameras: tuple[Camera, ...]
    segments: dict[int, IntArray] = field(default_factory=dict)
    support: tuple[FloatArray, float] | None = None
    depths: tuple[FloatArray, ...] = ()  # per camera: (h, w) mm, NaN where nothing returned
    labels: tuple[IntArray, ...] = ()
    sigma: FloatArray | None = None

    def of_views(self, views: Iterable[int]) -> Scan:
        """The part of the scan seen by these views (their cameras kept in order)."""
        chosen = sorted(set(views))
        keep = np.isin(self.view, chosen)
        index = np.cumsum(keep) - 1
        segments = {k: index[v[keep[v]]] for k, v in self.segments.items() if keep[v].any()}
        return Scan(self.points[keep], self.view[keep],
                    tuple(self.cameras[v] for v in chosen), segments, self.support,
                    tuple(self.depths[v] for v in chosen) if self.depths else (),
                    tuple(self.labels[v] for v in chosen) if self.labels else (),
                    None if self.sigma is None else self.sigma[keep])

    def near(self, centre: FloatArray, radius: float) -> IntArray:
        """The indices of the points within ``radius`` of ``centre`` (ascending): the
        exact test on the slab of points whose x lies that near, looked up in the points
        sorted by x, not on every point (a part is small beside a scan of its assembly)."""
        order, xs = self._by_x
        c = np.asarray(centre, dtype=np.float64)
        # (a slab a hair wider than the radius: every point the test passes lies in it)
        lo, hi = np.searchsorted(xs, [c[0] - radius - 1e-6, c[0] + radius + 1e-6])
        slab = order[lo:hi]
        out: IntArray = np.sort(slab[np.sum((self.points[slab] - c) ** 2, axis=1)
                                     <= radius * radius])
        return out

    @cached_property
    def _by_x(self) -> tuple[IntArray, FloatArray]:
        order = np.argsort(self.points[:, 0], kind="stable")
        return order, self.points[order, 0]

    def without(self, used: npt.NDArray[np.bool_]) -> Scan:
        """The scan without the points of ``used`` (n,) bool."""
        keep = ~used
        index = np.cumsum(keep) - 1
        segments = {k: index[v[keep[v]]] for k, v in self.segments.items() if keep[v].any()}
        return Scan(self.points[keep], self.view[keep], self.cameras, segments, self.support,
                    self.depths, self.labels, None if self.sigma is None else self.sigma[keep])

    def sigma_of(self, index: npt.NDArray[np.bool_] | IntArray) -> FloatArray | None:
        """The depth sigmas of the points ``index`` picks (a mask or indices); None where
        the scan has none."""
        return None if self.sigma is None else self.sigma[index]


def scan_of(frames: Sequence[RgbdFrame], cfg: ScanConfig = ScanConfig()) -> Scan:
    """The inspection's points of some frames: back-projected (mm), the support plane removed,
    each instance's points apart where the frames carry ids (0 is the support).

    Raises:
        ValueError: no frame, or no valid depth in any.
    """
    if not frames:
        raise ValueError("a scan needs at least one frame")
    cameras = tuple(camera_of(f.intrinsics, f.world_to_camera) for f in frames)
    points, views, ids, sigmas = [], [], [], []
    for k, frame in enumerate(frames):
        mask = None if frame.instance is None else frame.instance > 0
        pts = backproject(frame, mask) * MM_PER_M
        label = np.asarray(frame.instance[_valid(frame) & mask], dtype=np.int64) \
            if frame.instance is not None and mask is not None else np.full(len(pts), -1)
        pts, label = _voxel(pts, label, cfg.voxel_mm)
        depth_m = cameras[k].project(pts)[1] / MM_PER_M
        sigmas.append(cfg.sensor.depth_sigma_m(depth_m) * MM_PER_M)
        points.append(pts)
        views.append(np.full(len(pts), k))
        ids.append(label)
    cloud, view, label = np.concatenate(points), np.concatenate(views), np.concatenate(ids)
    sigma = np.concatenate(sigmas)
    if not len(cloud):
        raise ValueError("no valid depth in the frames")
    support = None
    if all(f.instance is None for f in frames):  # no ids: find the support to take it away
        support = support_plane(cloud, cfg)
        if support is not None:
            # what lies on the support or under it (the table's edge, the floor) goes
            keep = cloud @ support[0] - support[1] > cfg.plane_mm
            cloud, view, label, sigma = cloud[keep], view[keep], label[keep], sigma[keep]
    segments = {int(i): np.flatnonzero(label == i) for i in np.unique(label) if i > 0}
    depths = tuple(np.where(_valid(f), f.depth.astype(np.float64) * MM_PER_M, np.nan)
                   for f in frames)
    labels = tuple(np.asarray(f.instance, dtype=np.int64) for f in frames) \
        if all(f.instance is not None for f in frames) else ()
    return Scan(cloud, view.astype(np.int64), cameras, segments, support, depths, labels, sigma)


def consistency(points: FloatArray, scan: Scan, tolerance_mm: float = 4.0,
                segment: int | None = None) -> float:
    """How well a hypothesis's surface points (n, 3, world mm: what the cameras would see of a
    part at a pose) agree with the depth the cameras returned: of the points whose pixel holds
    a depth, the share not contradicted by it. A point is contradicted when the camera saw
    farther than it (free space where the part would stand); nearer is another part hiding it,
    and counts neither way.

    With ``segment`` (the instance of a segmented scan the hypothesis is of), a point is
    supported only where its pixel is the segment's; one whose pixel another instance holds
    at its depth or beyond it (within the tolerance) is contradicted too: that surface is the
    other part's, or free space in front of it. A nut's shape laid over a stud's end, its
    faces on the real nut beside it, agrees with the depth everywhere; the stud, whose hidden
    length lies behind the nut, loses nothing by it, nor a ball behind its cage. 1.0 where
    nothing can be checked."""
    supported = contradicted = 0
    labels = scan.labels if segment is not None and scan.labels else (None,) * len(scan.depths)
    points = np.ascontiguousarray(points, dtype=np.float64)
    for camera, depth, label in zip(scan.cameras, scan.depths, labels, strict=True):
        k = camera.intrinsics
        agrees, farther = _depth_counts(
            points, np.ascontiguousarray(camera.world_to_camera, dtype=np.float64),
            float(k.fx), float(k.fy), float(k.cx), float(k.cy), depth,
            _NO_LABELS if label is None else label, -1 if segment is None else int(segment),
            float(tolerance_mm))
        supported += agrees
        contradicted += farther
    total = supported + contradicted
    return supported / total if total else 1.0


_NO_LABELS = np.zeros((0, 0), dtype=np.int64)


@numba.njit(nogil=True, cache=True)
def _depth_counts(points: Any, w2c: Any, fx: float, fy: float, cx: float,  # noqa: PLR0913
                  cy: float, depth: Any, label: Any, segment: int, tolerance: float) -> Any:
    """``consistency``'s counts for one camera: the points the depth at their pixel agrees
    with, and those it contradicts (``label``: the instance of each pixel, empty: none)."""
    height, width = depth.shape
    agrees = farther = 0
    for i in range(len(points)):
        p0, p1, p2 = points[i, 0], points[i, 1], points[i, 2]
        x = p0 * w2c[0, 0] + p1 * w2c[0, 1] + p2 * w2c[0, 2] + w2c[0, 3]
        y = p0 * w2c[1, 0] + p1 * w2c[1, 1] + p2 * w2c[1, 2] + w2c[1, 3]
        z = p0 * w2c[2, 0] + p1 * w2c[2, 1] + p2 * w2c[2, 2] + w2c[2, 3]
        if not z > 0:
            continue
        u, v = np.rint(fx * x / z + cx), np.rint(fy * y / z + cy)
        if not (0 <= u < width and 0 <= v < height):
            continue
        seen = depth[int(v), int(u)]
        if not np.isfinite(seen):
            continue
        gap = seen - z
        agree, far = abs(gap) <= tolerance, gap > tolerance
        if label.shape[0] > 0 and label[int(v), int(u)] != segment:
            agree, far = False, far or gap >= 0
        agrees += agree
        farther += far
    return agrees, farther


def _valid(frame: RgbdFrame) -> npt.NDArray[np.bool_]:
    return np.isfinite(frame.depth) & (frame.depth > 0)


def _voxel(points: FloatArray, label: npt.NDArray[np.int64], voxel: float
           ) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """One point per voxel and instance (the mean of its points)."""
    if voxel <= 0 or not len(points):
        return points, label
    out_p, out_l = [], []
    for i in np.unique(label):
        pts = voxel_down(points[label == i], voxel)
        out_p.append(pts)
        out_l.append(np.full(len(pts), i))
    return np.concatenate(out_p), np.concatenate(out_l)


def support_plane(points: FloatArray, cfg: ScanConfig = ScanConfig()
                  ) -> tuple[FloatArray, float] | None:
    """The largest plane facing up (within ``plane_normal_deg`` of +Z) that most points lie
    on, below most of the cloud: (unit normal, offset); None where none is found. Seeded."""
    rng = np.random.default_rng(0)
    if len(points) < 3:
        return None
    best, best_count = None, 0
    cos_max = np.cos(np.radians(cfg.plane_normal_deg))
    for _ in range(cfg.plane_iterations):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm == 0:
            continue
        n = n / norm * (1 if n[2] >= 0 else -1)
        if n[2] < cos_max:
            continue
        offset = float(n @ a)
        count = int((np.abs(points @ n - offset) <= cfg.plane_mm).sum())
        if count > best_count:
            best, best_count = (n, offset), count
    if best is None:
        return None
    n, offset = best
    near = np.abs(points @ n - offset) <= cfg.plane_mm
    # least squares on the inliers, and the parts above it
    centre = points[near].mean(axis=0)
    _, _, vt = np.linalg.svd(points[near] - centre, full_matrices=False)
    normal = vt[2] * (1 if vt[2][2] >= 0 else -1)
    return normal, float(normal @ centre)
