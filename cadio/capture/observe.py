"""What a camera knows of a part: the grid it places, the inputs in it, the carve baseline.

The learned stages must see only what a real scan knows: a part's segmented observed points and
the cameras that saw them (intrinsics, extrinsics, gravity along world -Z). Never its pose, its
bounding box or its truth grid. This module places the learning grid from that alone, by one
documented rule (``GridRule``), and builds every input in it:

- the **observed** protocol (the headline): a cube whose axes are the first view's observer
  frame (x right, y away from the camera along the ground, z up: DESIGN.md's frame) and whose
  centre and side come from the observed points of the views given (``place_grid``);
- the **oracle-box** protocol (the paper's setting, a labelled comparison only): the part's own
  truth grid, the cube around its CAD bounding box, placed with the true pose (``oracle_grid``).

In either grid: ``observed_occupancy`` bins the points, ``depth_view`` renders them as a 2D
depth image along +y (the input of the ``r2n2`` baseline) and ``carve`` is the ``carve``
baseline (no learning: what lies behind the observed surface along each camera ray, carved by
every view). The truth is voxelized into the same grid by ``truth_occupancy``, for the loss and
the score only; ``cadio.capture.examples`` checks that no truth reaches the inputs.

Lengths are metres in the world frame of the capture (the scene scaled by ``scale_m_per_mm``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cadio.cad.voxels import occupancy_in, voxel_centres
from cadio.records import CameraIntrinsics, FloatArray, Mesh
from cadio.truth.relations import view_frame

BoolGrid = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class GridRule:
    """The one rule that places the observed-protocol grid from the observed points.

    In the first view's observer frame, the observed points span [lo, hi]. Across the view
    (x) and vertically (z) the part is taken to span what was seen. Along the view (y) the
    camera sees only the front: the part is assumed to reach ``depth_prior`` times its largest
    seen extent behind the nearest observed point (a part is about as deep as it is wide), or
    what was seen, if more. The cube is centred on that estimated box and its side is the
    box's largest extent times ``1 + margin``, so the completed shape has room.
    """

    depth_prior: float = 1.0
    margin: float = 0.15


@dataclass(frozen=True)
class CubeGrid:
    """A cube in the world: ``rotation`` (3, 3) has the grid axes x, y, z as columns (world,
    unit), ``corner`` (3,) is the world position of the cube's (0, 0, 0) corner, ``side`` its
    edge (metres). The same cube serves every resolution n."""

    rotation: FloatArray
    corner: FloatArray
    side: float

    def grid_to_world(self, n: int) -> FloatArray:
        """(4, 4): homogeneous voxel index (i, j, k, 1) -> voxel centre in the world."""
        size = self.side / n
        m = np.eye(4)
        m[:3, :3] = self.rotation * size
        m[:3, 3] = self.corner + self.rotation @ np.full(3, size / 2)
        return m

    def to_grid(self, points_world: FloatArray) -> FloatArray:
        """Points (m, 3) world -> cube coordinates in [0, 1]^3 inside the cube."""
        return (np.asarray(points_world, dtype=np.float64) - self.corner) @ self.rotation / (
            self.side)

    def voxel_m(self, n: int) -> float:
        return self.side / n


def observer_rotation(world_to_camera: FloatArray) -> FloatArray:
    """(3, 3) columns right, behind, up (world): the observer frame of a camera.

    The camera's forward axis projected on the ground is "behind" (DESIGN.md); gravity is world
    -Z, as the captures' world frames are.
    """
    forward = np.asarray(world_to_camera, dtype=np.float64)[2, :3]  # camera z axis in world
    return view_frame(forward).T


def camera_azimuth_deg(world_to_camera: FloatArray) -> float:
    """Azimuth of a camera's view about world Z, degrees in [0, 360): 0 looking along +Y,
    counter-clockwise seen from above (the capture circle's convention)."""
    forward = np.asarray(world_to_camera, dtype=np.float64)[2, :3]
    return float(np.degrees(np.arctan2(-forward[0], forward[1])) % 360.0)


def place_grid(points_world: FloatArray, world_to_camera: FloatArray,
               rule: GridRule = GridRule()) -> CubeGrid:
    """The observed-protocol cube of a part from its observed points and the first camera.

    Args:
        points_world: (m, 3) observed points of the part in all views given, world metres.
        world_to_camera: (4, 4) the first view's camera (its observer frame orients the cube).
        rule: the placement rule.

    Raises:
        ValueError: fewer than one point, or a vertical camera (no observer frame).
    """
    pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        raise ValueError("no observed point to place a grid on")
    rot = observer_rotation(world_to_camera)
    local = pts @ rot  # observer-frame coordinates
    lo, hi = local.min(axis=0), local.max(axis=0)
    seen = hi - lo
    depth = max(seen[1], rule.depth_prior * max(seen[0], seen[2]))
    box_lo = lo.copy()
    box_hi = np.array([hi[0], lo[1] + depth, hi[2]])
    side = max(float(np.max(box_hi - box_lo)), 1e-6) * (1.0 + rule.margin)
    centre = (box_lo + box_hi) / 2
    return CubeGrid(rotation=rot, corner=rot @ (centre - side / 2), side=side)


def oracle_grid(mesh: Mesh, part_to_world: FloatArray, margin: float) -> CubeGrid:
    """The oracle-box protocol: the part's truth grid (cube around its CAD bounding box, part
    axes), placed in the world with the true pose. A comparison with the paper's setting only.

    Args:
        mesh: the part, mm, part coordinates. part_to_world: (4, 4) mm -> world metres
            (pose and scale). margin: ``Tolerances.grid_margin``, as the ingest's grids.
    """
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    side_mm = float(np.max(hi - lo)) * (1.0 + margin)
    corner_mm = (lo + hi) / 2 - side_mm / 2
    linear = np.asarray(part_to_world, dtype=np.float64)[:3, :3]
    scale = float(np.cbrt(abs(np.linalg.det(linear))))
    return CubeGrid(rotation=linear / scale,
                    corner=linear @ corner_mm + part_to_world[:3, 3], side=side_mm * scale)


def observed_occupancy(points_world: FloatArray, grid: CubeGrid, n: int) -> BoolGrid:
    """(n, n, n) bool: voxels of the cube holding at least one observed point."""
    ijk = np.floor(grid.to_grid(points_world) * n).astype(np.int64)
    keep = np.all((ijk >= 0) & (ijk < n), axis=1)
    out = np.zeros((n, n, n), dtype=bool)
    out[ijk[keep, 0], ijk[keep, 1], ijk[keep, 2]] = True
    return out


def depth_view(points_world: FloatArray, grid: CubeGrid, d: int) -> npt.NDArray[np.float32]:
    """(2, d, d) float32: the observed points as a depth image of the cube seen along +y.

    Channel 0: distance along +y of the nearest point in each (x, z) cell, as a fraction of
    the side (1 where nothing was seen); channel 1: 1 where something was seen. Indexed [x, z].
    """
    g = grid.to_grid(points_world)
    inside = np.all((g >= 0) & (g < 1), axis=1)
    g = g[inside]
    cell = np.floor(g[:, [0, 2]] * d).astype(np.int64)
    depth = np.ones((d, d), dtype=np.float32)
    np.minimum.at(depth, (cell[:, 0], cell[:, 1]), g[:, 1].astype(np.float32))
    mask = np.zeros((d, d), dtype=np.float32)
    mask[cell[:, 0], cell[:, 1]] = 1.0
    return np.stack([depth, mask])


@dataclass(frozen=True)
class ViewEvidence:
    """One view as the carve baseline needs it: depth (h, w) metres (0 = no return), the part's
    pixels (h, w) bool (segmented), the camera, and the support plane the view saw (unit
    normal pointing up (3,), offset d: n . p = d, world metres; None when it saw none)."""

    depth: npt.NDArray[np.float32]
    mask: npt.NDArray[np.bool_]
    intrinsics: CameraIntrinsics
    world_to_camera: FloatArray
    support: tuple[FloatArray, float] | None = None


def carve(views: list[ViewEvidence], grid: CubeGrid, n: int) -> BoolGrid:
    """The ``carve`` baseline: occupied where some view saw the part's surface in front of the
    voxel and no view saw through it.

    Per view, a voxel centre projecting onto a pixel with a depth return is *free* when it lies
    in front of that return (the ray passed through it), *behind the part* when the pixel is
    the part's and the voxel lies at or behind its surface, and unknown otherwise (behind
    another surface, outside the image, no return). Half a voxel diagonal of slack keeps the
    surface voxels themselves. Nothing lies inside the support plane a view saw: voxels below
    it are free too (the camera saw the table; parts rest on it or above it).
    """
    centres = voxel_centres(grid.grid_to_world(n), n).reshape(-1, 3)
    free = np.zeros(len(centres), dtype=bool)
    behind = np.zeros(len(centres), dtype=bool)
    slack = np.float32(0.5 * np.sqrt(3.0) * grid.voxel_m(n))
    for view in views:
        depth_at, mask_at, z = _project(view, centres)
        seen = depth_at > 0
        front = z < depth_at - slack
        free |= seen & front
        behind |= mask_at & ~front
        if view.support is not None:
            normal, offset = view.support
            free |= centres @ normal.astype(np.float32) < np.float32(offset) - slack
    return (behind & ~free).reshape(n, n, n)


def _project(view: ViewEvidence, points: npt.NDArray[np.float32]) -> tuple[
        npt.NDArray[np.float32], npt.NDArray[np.bool_], npt.NDArray[np.float32]]:
    """(depth at the pixel (0 outside the image or without a return), the part's mask at the
    pixel, camera z) of each world point (float32: this runs on 262k points per view)."""
    w2c = np.asarray(view.world_to_camera, dtype=np.float32)
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    k = view.intrinsics
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(z > 1e-9, np.float32(1.0) / z, np.float32(np.nan))
        u = np.floor(cam[:, 0] * inv * np.float32(k.fx) + np.float32(k.cx + 0.5))
        v = np.floor(cam[:, 1] * inv * np.float32(k.fy) + np.float32(k.cy + 0.5))
        inside = (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    flat = np.where(inside, v * k.width + u, 0).astype(np.int64)
    depth = np.nan_to_num(view.depth.ravel()[flat].astype(np.float32), nan=0.0)
    depth[~inside] = 0.0
    mask = view.mask.ravel()[flat] & inside
    return depth, mask, z


def truth_occupancy(mesh: Mesh, part_to_world: FloatArray, grid: CubeGrid, n: int) -> BoolGrid:
    """The part's solid in the cube (for the loss and the score only: it uses the true pose).

    Args:
        mesh: the part, mm, part coordinates. part_to_world: (4, 4) part mm -> world metres.
    """
    grid_to_part = np.linalg.inv(np.asarray(part_to_world, dtype=np.float64)) @ (
        grid.grid_to_world(n))
    return occupancy_in(mesh, grid_to_part, n)
