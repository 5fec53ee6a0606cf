"""Separating parts in a frame without instance ids, and scoring a segmentation against the ids.

A real recording has no instance-id image: the support plane is found by RANSAC and removed with
what lies behind it, and the remaining points are clustered with open3d's DBSCAN.
``segmentation_score`` measures how well that recovers the ids on simulated captures.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import open3d as o3d
from scipy.optimize import linear_sum_assignment

from cadio.capture.pointcloud import IntImage, backproject, valid_depth
from cadio.records import FloatArray, RgbdFrame


@dataclass(frozen=True)
class SegmentConfig:
    """Plane removal and clustering when a capture has no instance ids. Lengths in metres."""

    # Inlier band of the support plane. Points of the parts' feet inside it are lost, so keep
    # it thin: noisy plane points that leak above it are sparse and DBSCAN drops them (5 mm
    # held up to sigma = 7 mm at 1.6 m; 3 mm did not).
    plane_distance_m: float = 0.005
    plane_iterations: int = 200
    plane_sample: int = 4000  # candidate planes are scored on this many points
    dbscan_eps_m: float = 0.012  # > 4 px footprints at 1.6 m, < the gaps between parts
    dbscan_min_points: int = 10
    min_cluster_points: int = 100  # smaller clusters are noise or plane fragments
    seed: int = 0


def fit_plane(points: FloatArray, cfg: SegmentConfig) -> tuple[FloatArray, float]:
    """Dominant plane by RANSAC (seeded), refined by least squares on its inliers.

    Returns:
        (unit normal (3,), offset d) with n . p = d for points p on the plane (metres).
    """
    rng = np.random.default_rng(cfg.seed)
    sample = points[rng.choice(len(points), min(len(points), cfg.plane_sample), replace=False)]
    best, best_count = (np.array([0.0, 0.0, 1.0]), 0.0), -1
    for _ in range(cfg.plane_iterations):
        a, b, c = sample[rng.choice(len(sample), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-12:
            continue
        n /= np.linalg.norm(n)
        count = int(np.count_nonzero(np.abs(sample @ n - n @ a) <= cfg.plane_distance_m))
        if count > best_count:
            best, best_count = (n, float(n @ a)), count
    inliers = points[np.abs(points @ best[0] - best[1]) <= cfg.plane_distance_m]
    centre = inliers.mean(axis=0)
    n = np.linalg.svd(inliers - centre, full_matrices=False)[2][2]
    return n, float(n @ centre)


def segment_clusters(frame: RgbdFrame, cfg: SegmentConfig | None = None) -> IntImage:
    """Parts without instance ids: drop the support plane and what lies behind it, cluster.

    Returns:
        (h, w) int32 labels: 0 for missing depth, plane and noise; 1..k for clusters, largest
        first. Labels are arbitrary: match them to parts with ``segmentation_score``.
    """
    cfg = cfg or SegmentConfig()
    valid = valid_depth(frame)
    pts = backproject(frame, valid)
    labels = np.zeros(frame.depth.shape, dtype=np.int32)
    if len(pts) < 3:
        return labels
    n, d = fit_plane(pts, cfg)
    eye = np.linalg.inv(frame.world_to_camera)[:3, 3]
    side = 1.0 if eye @ n - d > 0 else -1.0  # distances measured towards the camera
    above = side * (pts @ n - d) > cfg.plane_distance_m
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[above]))
    found = np.asarray(cloud.cluster_dbscan(cfg.dbscan_eps_m, cfg.dbscan_min_points))
    ids, counts = np.unique(found[found >= 0], return_counts=True)
    by_size = np.argsort(-counts, kind="stable")
    order = ids[by_size][counts[by_size] >= cfg.min_cluster_points]
    remap = np.zeros(max(int(found.max(initial=-1)) + 2, 1), dtype=np.int32)
    remap[order + 1] = np.arange(1, len(order) + 1, dtype=np.int32)
    flat = np.zeros(len(pts), dtype=np.int32)
    flat[above] = remap[found + 1]
    labels[valid] = flat
    return labels


@dataclass(frozen=True)
class SegmentationScore:
    """Agreement of predicted labels with true instance ids.

    iou: per true instance id, IoU of its pixels with the cluster matched to it (one-to-one,
    Hungarian on IoU); mean_iou over the true parts; ari: adjusted Rand index over the pixels
    that are foreground in the truth or the prediction (valid depth only).
    """

    iou: dict[int, float]
    mean_iou: float
    ari: float


def _pairs(counts: npt.NDArray[np.int64]) -> float:
    return float(np.sum(counts * (counts - 1)) / 2)


def adjusted_rand_index(a: npt.NDArray[Any], b: npt.NDArray[Any]) -> float:
    """Adjusted Rand index of two labelings of the same items (1 = identical partitions)."""
    _, ai = np.unique(a, return_inverse=True)
    _, bi = np.unique(b, return_inverse=True)
    table = np.zeros((ai.max(initial=0) + 1, bi.max(initial=0) + 1), dtype=np.int64)
    np.add.at(table, (ai, bi), 1)
    index, rows, cols = _pairs(table), _pairs(table.sum(1)), _pairs(table.sum(0))
    total = _pairs(np.array([len(ai)]))
    expected = rows * cols / total if total else 0.0
    top = (rows + cols) / 2 - expected
    return 1.0 if top == 0 else (index - expected) / top


def segmentation_score(labels: IntImage, instance: IntImage,
                       valid: npt.NDArray[np.bool_] | None = None) -> SegmentationScore:
    """Score predicted labels (0 = background) against true instance ids (0 = background)."""
    keep = np.ones(labels.shape, dtype=bool) if valid is None else valid
    truth_ids = [int(i) for i in np.unique(instance[keep]) if i > 0]
    pred_ids = [int(i) for i in np.unique(labels[keep]) if i > 0]
    ious = np.zeros((len(truth_ids), max(len(pred_ids), 1)))
    for r, t in enumerate(truth_ids):
        tm = keep & (instance == t)
        for c, p in enumerate(pred_ids):
            pm = keep & (labels == p)
            ious[r, c] = np.count_nonzero(tm & pm) / max(int(np.count_nonzero(tm | pm)), 1)
    rows, cols = linear_sum_assignment(-ious)
    iou = {t: 0.0 for t in truth_ids}
    iou.update({truth_ids[r]: float(ious[r, c]) for r, c in zip(rows, cols, strict=True)})
    fg = keep & ((instance > 0) | (labels > 0))
    return SegmentationScore(iou, float(np.mean(list(iou.values()))) if iou else 1.0,
                             adjusted_rand_index(instance[fg], labels[fg]))
