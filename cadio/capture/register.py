"""Registering a completed shape back onto the scan it came from (ICP, as the paper does).

The completion network answers in its grid; small placement errors of the grid show as an
offset between the completed surface and the observed points. ``register`` runs open3d's
point-to-point ICP from the observed points (the scan) to the completed surface, and returns
the rigid motion that moves the completion onto the scan with the residual: the RMS distance of
the matched scan points, in the world's units. The residual is what the report shows: a scan
that the completion explains well leaves a residual near the sensor noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from cadio.records import FloatArray


@dataclass(frozen=True)
class Registration:
    """transform (4, 4): apply to the completion to lay it on the scan. fitness: share of scan
    points matched within ``max_distance``; residual: their RMS distance (world units)."""

    transform: FloatArray
    fitness: float
    residual: float


def register(completed: FloatArray, scan: FloatArray, max_distance: float,
             iterations: int = 50) -> Registration:
    """ICP of the scan points (m, 3) onto the completed surface points (k, 3), both world.

    Args:
        max_distance: correspondences farther than this are ignored (world units); two or
            three voxels of the completion grid is a sensible value.

    Raises:
        ValueError: an empty point set.
    """
    if len(completed) == 0 or len(scan) == 0:
        raise ValueError("registration needs points on both sides")
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(scan, np.float64)))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        np.asarray(completed, np.float64)))
    result = o3d.pipelines.registration.registration_icp(
        source, target, max_distance, np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPoint(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=iterations))
    scan_to_completion = np.asarray(result.transformation, dtype=np.float64)
    back: FloatArray = np.linalg.inv(scan_to_completion).astype(np.float64)
    return Registration(transform=back,
                        fitness=float(result.fitness), residual=float(result.inlier_rmse))
