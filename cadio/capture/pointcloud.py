"""From RGB-D frames to per-part point clouds and point samples.

Depth is back-projected to points in the frame's world frame, in **metres** (the capture's
world is the scene frame scaled by ``scale_m_per_mm``). The ground truth of a part lives in its
own millimetre coordinates, so ``to_part_frame`` undoes the scale and the part's pose: that
needs the truth, so it serves checks against the CAD only; the learning inputs are built from
the world points and the cameras alone (``cadio.capture.observe``). Parts are separated with
the instance ids when a capture has them, else with the labels of ``cadio.capture.segment``.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from cadio.records import FloatArray, RgbdFrame, apply_pose

IntImage = npt.NDArray[np.int32]


def valid_depth(frame: RgbdFrame) -> npt.NDArray[np.bool_]:
    """(h, w) bool: pixels with a finite, positive depth."""
    return np.isfinite(frame.depth) & (frame.depth > 0)


def backproject(frame: RgbdFrame, mask: npt.NDArray[np.bool_] | None = None,
                stride: int = 1) -> FloatArray:
    """Points seen by the pixels of ``mask`` (and with valid depth), in world metres; with
    ``stride``, every stride-th of them only (the same points as ``[::stride]`` of all, at a
    stride-th of the cost: a support plane is fitted to a sample of the table's returns).

    Returns:
        (n, 3) float64 metres, world frame, in row-major pixel order of ``mask & valid``.
    """
    keep = valid_depth(frame) if mask is None else valid_depth(frame) & mask
    v, u = (axis[::stride] for axis in np.nonzero(keep))
    k = frame.intrinsics
    z = frame.depth[v, u].astype(np.float64)
    cam = np.column_stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z])
    return apply_pose(np.asarray(np.linalg.inv(frame.world_to_camera), dtype=np.float64), cam)


def to_part_frame(points_m: FloatArray, pose_mm: FloatArray, scale_m_per_mm: float) -> FloatArray:
    """World points (metres) to a part's own coordinates (millimetres).

    Args:
        points_m: (n, 3) world metres.
        pose_mm: (4, 4) part -> scene, mm (the scene's ``pose_mm``).
        scale_m_per_mm: the capture's scale (``scene_meta["scale_m_per_mm"]``).
    Returns:
        (n, 3) float64 mm in part coordinates.
    """
    return apply_pose(np.linalg.inv(np.asarray(pose_mm, dtype=np.float64)),
                      np.asarray(points_m, dtype=np.float64) / scale_m_per_mm)


def part_clouds(frame: RgbdFrame, scene: dict[str, Any],
                labels: IntImage | None = None) -> dict[int, FloatArray]:
    """Each part's observed points in its own coordinates, mm, keyed by instance id.

    Args:
        frame: a frame with instance ids (or pass ``labels``, an (h, w) image of the same ids).
        scene: the capture's scene description (``read_scene_meta`` / ``capture.scene_meta``).
    Raises:
        ValueError: when neither the frame nor ``labels`` give per-pixel ids.
    """
    ids = frame.instance if labels is None else labels
    if ids is None:
        raise ValueError("frame has no instance ids: segment it first (segment_clusters)")
    scale = float(scene["scale_m_per_mm"])
    return {int(p["instance_id"]): to_part_frame(backproject(frame, ids == p["instance_id"]),
                                                 np.asarray(p["pose_mm"]), scale)
            for p in scene["parts"]}


def sample_points(points: FloatArray, k: int = 600, seed: int = 0,
                  method: str = "fps") -> FloatArray:
    """k points of a cloud for the relation network (the paper samples 600 per part).

    Args:
        points: (n, 3), any unit; n >= 1.
        method: "fps" (farthest point sampling from a seeded random start) or "random".
    Returns:
        (k, 3), same unit; when n < k, every point plus seeded random repeats.
    Raises:
        ValueError: on an empty cloud or an unknown method.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        raise ValueError("cannot sample an empty point cloud")
    if method not in ("fps", "random"):
        raise ValueError(f"unknown sampling method {method!r}")
    rng = np.random.default_rng(seed)
    if len(pts) <= k:
        extra = rng.choice(len(pts), k - len(pts), replace=True)
        return np.concatenate([pts, pts[extra]])
    if method == "random":
        return pts[np.sort(rng.choice(len(pts), k, replace=False))]
    return pts[_farthest(np.ascontiguousarray(pts), k, int(rng.integers(len(pts))))]


@numba.njit(nogil=True, cache=True)
def _farthest(pts: FloatArray, k: int, start: int) -> npt.NDArray[np.int64]:  # pragma: no cover
    """Farthest point sampling from ``start``: k indices. One compiled pass over the cloud per
    point chosen (numpy made three temporaries of it each time: the relation inputs of a night
    spent seconds here); the same sums in the same order as numpy's, so the same choice."""
    n = len(pts)
    chosen = np.empty(k, dtype=np.int64)
    chosen[0] = start
    dist = np.empty(n, dtype=np.float64)
    for j in range(n):
        dx, dy, dz = pts[j, 0] - pts[start, 0], pts[j, 1] - pts[start, 1], pts[j, 2] - pts[
            start, 2]
        dist[j] = dx * dx + dy * dy + dz * dz
    for i in range(1, k):
        best = 0
        for j in range(1, n):
            if dist[j] > dist[best]:  # the first of equal maxima, as np.argmax
                best = j
        chosen[i] = best
        for j in range(n):
            dx, dy, dz = pts[j, 0] - pts[best, 0], pts[j, 1] - pts[best, 1], pts[j, 2] - pts[
                best, 2]
            dist[j] = min(dist[j], dx * dx + dy * dy + dz * dz)
    return chosen
