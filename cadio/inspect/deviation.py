"""Scan to CAD: each pixel's signed distance from the registered CAD, as inspection software
colours it.

For one view, every pixel whose depth the camera returned (the support taken away) is
back-projected and measured against the CAD surface of the registered parts: the distance
along the surface's outward normal to the nearest point the camera would see of them (positive:
material where the CAD has none, in front of its surface). The image, and the share of its
points within a tolerance, say at a glance where the assembly departs from its design.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from cadio.capture.pointcloud import valid_depth
from cadio.inspect.scan import ScanConfig, support_plane
from cadio.inspect.surface import MM_PER_M, PartSurface, camera_of, occluders, visible
from cadio.records import FloatArray, RgbdFrame, apply_pose

FAR_MM = 10.0  # a pixel farther than this from every registered surface is left blank


def deviation_image(parts: Sequence[PartSurface], poses: Mapping[int, FloatArray],
                    frame: RgbdFrame, cfg: ScanConfig | None = None
                    ) -> npt.NDArray[np.float32]:
    """(h, w) float32 mm: each pixel's signed distance from the registered CAD (NaN where the
    camera returned no depth, on the support, or farther than ``FAR_MM`` from every part)."""
    camera = camera_of(frame.intrinsics, frame.world_to_camera)
    keep = valid_depth(frame)
    if frame.instance is not None:
        keep &= frame.instance > 0
    v, u = np.nonzero(keep)
    k = frame.intrinsics
    z = frame.depth[v, u].astype(np.float64) * MM_PER_M
    cam = np.column_stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z])
    points = apply_pose(np.asarray(np.linalg.inv(camera.world_to_camera), np.float64), cam)
    if frame.instance is None:
        support = support_plane(points, cfg or ScanConfig())
        if support is not None:
            off = np.abs(points @ support[0] - support[1]) > (cfg or ScanConfig()).plane_mm
            points, v, u = points[off], v[off], u[off]
    out = np.full((k.height, k.width), np.nan, dtype=np.float32)
    if not len(points) or not poses:
        return out
    others = occluders([(i, parts[i].mesh, pose) for i, pose in poses.items()])
    surface, normals = [], []
    for i, pose in poses.items():
        pts, nrm = visible(parts[i], pose, [camera], 1, (others, i))
        surface.append(pts)
        normals.append(nrm)
    model, model_n = np.concatenate(surface), np.concatenate(normals)
    if not len(model):
        return out
    dist, idx = cKDTree(model).query(points, distance_upper_bound=FAR_MM)
    near = np.isfinite(dist)
    signed = np.einsum("ij,ij->i", model_n[idx[near]], points[near] - model[idx[near]])
    out[v[near], u[near]] = signed.astype(np.float32)
    return out


def within(image: npt.NDArray[np.float32], tolerance_mm: float) -> float:
    """The share of the image's measured pixels within the tolerance of the CAD."""
    values = image[np.isfinite(image)]
    return float(np.mean(np.abs(values) <= tolerance_mm)) if len(values) else float("nan")
