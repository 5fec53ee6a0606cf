"""A part's CAD surface as registration reads it, and what a camera sees of it at a pose.

Registration fits scan points to the CAD surface the camera would see at the hypothesised pose
(``visible``: the part's mesh ray-cast from the capture's cameras, hit points with their
triangles' outward normals), not to the whole surface: points on the far side of a part would
pull a point-to-plane fit towards faces no pixel saw. Everything here is millimetres, in the
world frame of the capture (a capture's metres times 1000).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import numpy.typing as npt
import open3d as o3d

from cadio.evidence.cad_samples import facet_normals, sample_triangles
from cadio.records import CameraIntrinsics, FloatArray, Mesh, apply_pose

MM_PER_M = 1000.0


@dataclass(frozen=True)
class Camera:
    """One view's camera: its intrinsics and world -> camera (4, 4), millimetres."""

    intrinsics: CameraIntrinsics
    world_to_camera: FloatArray

    @property
    def centre(self) -> FloatArray:
        """(3,) the camera's position in the world, mm."""
        rot, t = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        centre: FloatArray = -rot.T @ t
        return centre

    def project(self, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Pixel coordinates (n, 2) and depths (n,) mm of world points (n, 3) mm."""
        cam = apply_pose(self.world_to_camera, points)
        k = self.intrinsics
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.column_stack([k.fx * cam[:, 0] / z + k.cx, k.fy * cam[:, 1] / z + k.cy])
        return uv, z


def camera_of(intrinsics: CameraIntrinsics, world_to_camera_m: FloatArray) -> Camera:
    """A ``Camera`` from a frame's intrinsics and its world -> camera in metres."""
    w2c = np.array(world_to_camera_m, dtype=np.float64)
    w2c[:3, 3] *= MM_PER_M
    return Camera(intrinsics, w2c)


@dataclass(frozen=True, eq=False)
class PartSurface:
    """A part's CAD surface in its own frame, mm: its mesh (triangles with outward normals),
    ``samples`` on it with their ``normals``, its centroid and diameter (the largest distance
    between two vertices, bounded by the box diagonal)."""

    part_id: str
    mesh: Mesh
    samples: FloatArray
    normals: FloatArray
    centre: FloatArray
    diameter: float
    _scene: list[Any] = field(default_factory=list, repr=False)

    @cached_property
    def radius(self) -> float:
        """The largest distance of the mesh from ``centre`` (every point of it lies within)."""
        return float(np.sqrt(np.max(np.sum((self.mesh.vertices - self.centre) ** 2, axis=1))))

    @cached_property
    def facet_normals(self) -> FloatArray:
        """(m, 3) the outward unit normal of each triangle of the mesh."""
        return facet_normals(self.mesh)

    def raycaster(self) -> Any:
        """The part's open3d ray-casting scene (built on first use)."""
        if not self._scene:
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(
                o3d.core.Tensor.from_numpy(np.ascontiguousarray(self.mesh.vertices, np.float32)),
                o3d.core.Tensor.from_numpy(np.ascontiguousarray(self.mesh.triangles, np.uint32)))
            self._scene.append(scene)
        return self._scene[0]


def part_surface(part_id: str, mesh: Mesh, samples: int = 20_000, seed: int = 0) -> PartSurface:
    """A part's surface for registration: ``samples`` area-weighted points with the outward
    normals of their triangles.

    Raises:
        ValueError: a mesh without area.
    """
    points, tris = sample_triangles(mesh, samples, seed)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    return PartSurface(part_id, mesh, points, facet_normals(mesh)[tris],
                       np.asarray(points.mean(axis=0), dtype=np.float64),
                       float(np.linalg.norm(hi - lo)))


@dataclass(frozen=True, eq=False)
class Occluders:
    """Parts placed in the world (mm) that may stand between a camera and another part: one
    ray-casting scene, and which of its geometries is which part (by index)."""

    scene: Any
    owner: tuple[int, ...]

    def first(self, rays: npt.NDArray[np.float32]) -> tuple[FloatArray, npt.NDArray[np.int64]]:
        """Per ray (n, 6: origin, unit direction, world mm) the distance to the first part it
        meets (inf: none) and that part's index (-1: none)."""
        hit = self.scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
        t = hit["t_hit"].numpy().astype(np.float64)
        geometry = hit["geometry_ids"].numpy().astype(np.int64)
        owner = np.array(self.owner, dtype=np.int64)
        found = np.isfinite(t)
        index = np.full(len(t), -1, dtype=np.int64)
        index[found] = owner[geometry[found]]
        return t, index


def occluders(parts: Sequence[tuple[int, Mesh, FloatArray]]) -> Occluders:
    """The ray-casting scene of parts (index, mesh in its own frame, part -> world pose)."""
    scene = o3d.t.geometry.RaycastingScene()
    owner = []
    for index, mesh, pose in parts:
        scene.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(apply_pose(pose, mesh.vertices),
                                                            np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(mesh.triangles, np.uint32)))
        owner.append(index)
    return Occluders(scene, tuple(owner))


def visible(part: PartSurface, pose: FloatArray, cameras: Sequence[Camera],
            stride: int = 1, hidden_by: tuple[Occluders, int] | None = None
            ) -> tuple[FloatArray, FloatArray]:
    """What the cameras see of the part placed at ``pose`` (part -> world, mm): the hit points
    (n, 3) and outward normals (n, 3), world mm, of every ``stride``-th pixel whose ray meets
    it. Alone, unless ``hidden_by`` (the other parts, and this part's index among them): then
    a ray that meets another part first (by more than a millimetre) sees nothing of it.
    """
    points, normals = [], []
    to_part: FloatArray = np.asarray(np.linalg.inv(pose), dtype=np.float64)
    for cam in cameras:
        rays = _rays_over(part, pose, cam, stride)
        if rays is None:
            continue
        origin, dirs = rays
        local_o = apply_pose(to_part, origin[None])[0]
        local_d = dirs @ to_part[:3, :3].T
        cast = part.raycaster().cast_rays(o3d.core.Tensor.from_numpy(_rays(local_o, local_d)))
        t = cast["t_hit"].numpy()
        hit = np.isfinite(t)
        if not hit.any():
            continue
        if hidden_by is not None:  # (only the rays that meet the part are cast again)
            others, index = hidden_by
            rows = np.flatnonzero(hit)
            t_first, first = others.first(_rays(origin, dirs[rows]))
            hit[rows] = (first == index) | (t[rows] <= t_first + 1.0)
            if not hit.any():
                continue
        tri = cast["primitive_ids"].numpy()[hit].astype(np.int64)
        pts = local_o + local_d[hit] * t[hit, None]
        nrm = part.facet_normals[tri]
        facing = np.einsum("ij,ij->i", nrm, local_d[hit]) < 0
        points.append(apply_pose(pose, pts[facing]))
        normals.append(nrm[facing] @ pose[:3, :3].T)
    if not points:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(points), np.concatenate(normals)


def _rays(origin: FloatArray, dirs: FloatArray) -> npt.NDArray[np.float32]:
    """(n, 6) float32 rays for open3d's ray casting: one origin (3,), directions (n, 3)."""
    out = np.empty((len(dirs), 6), dtype=np.float32)
    out[:, :3] = origin
    out[:, 3:] = dirs
    return out


def _rays_over(part: PartSurface, pose: FloatArray, cam: Camera, stride: int
               ) -> tuple[FloatArray, FloatArray] | None:
    """The camera's centre and unit ray directions (world) of the pixels over the part's
    projected bounding sphere that can meet the part (within its ``radius`` of its centre);
    None where it is behind the camera or off the image."""
    centre = apply_pose(pose, part.centre)
    (uv,), (z,) = cam.project(centre[None])
    if not np.isfinite(z) or z <= 0.5 * part.diameter:
        return None
    k = cam.intrinsics
    radius_px = 0.6 * part.diameter * max(k.fx, k.fy) / max(z - 0.5 * part.diameter, 1e-6)
    u0, u1 = int(max(0, uv[0] - radius_px)), int(min(k.width - 1, uv[0] + radius_px))
    v0, v1 = int(max(0, uv[1] - radius_px)), int(min(k.height - 1, uv[1] + radius_px))
    if u0 > u1 or v0 > v1:
        return None
    cam_dirs = _pixel_rays(k)[v0:v1 + 1:stride, u0:u1 + 1:stride].reshape(-1, 3)
    # a ray meets the part only within the cone from the camera around its bounding sphere
    # (a tenth of a micrometre wider): the window's corners, and all of it for a long part
    # seen end on, need no cast
    towards = apply_pose(cam.world_to_camera, centre[None])[0]
    distance = float(np.linalg.norm(towards))
    reach = part.radius + 1e-4
    if distance > reach:
        cone = np.sqrt(1.0 - (reach / distance) ** 2)
        cam_dirs = cam_dirs[cam_dirs @ (towards / distance) >= cone - 1e-9]
    rot = cam.world_to_camera[:3, :3]
    dirs: FloatArray = cam_dirs @ rot  # camera -> world: R^T d
    return cam.centre, dirs


_PIXEL_RAYS: dict[CameraIntrinsics, FloatArray] = {}


def _pixel_rays(k: CameraIntrinsics) -> FloatArray:
    """(height, width, 3) the unit ray of every pixel in the camera's frame, once per
    intrinsics."""
    table = _PIXEL_RAYS.get(k)
    if table is None:
        if len(_PIXEL_RAYS) > 8:
            _PIXEL_RAYS.clear()
        u, v = np.meshgrid(np.arange(k.width), np.arange(k.height))
        table = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones(u.shape)], axis=-1)
        table /= np.linalg.norm(table, axis=-1, keepdims=True)
        table.setflags(write=False)
        _PIXEL_RAYS[k] = table
    return table


def voxel_down(points: FloatArray, voxel_mm: float) -> FloatArray:
    """One point per occupied voxel (the mean of its points), for clouds of any density."""
    if len(points) == 0 or voxel_mm <= 0:
        return points
    keys = np.floor(points / voxel_mm).astype(np.int64)
    # the voxels as one integer each, in the order of their rows (x, then y, then z): a
    # row-wise unique sorts the same, several times slower
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    packed = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    _, inverse, counts = np.unique(packed, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse.ravel(), points)
    down: FloatArray = sums / counts[:, None]
    return down


def as_cloud(points: FloatArray, normals: FloatArray | None = None) -> Any:
    """An open3d point cloud of (n, 3) points (and normals)."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    return cloud


BoolArray = npt.NDArray[np.bool_]
