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

import numba
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
    def normal_offsets(self) -> FloatArray:
        """(k,) each sample's normal dotted with the sample: n . s."""
        out: FloatArray = np.einsum("ij,ij->i", self.normals, self.samples)
        return out

    @cached_property
    def principal_axes(self) -> FloatArray:
        """(3, 3) the part's principal axes as columns, the longest last (of every tenth
        sample)."""
        centred = self.samples[::10] - self.centre
        _, vectors = np.linalg.eigh(centred.T @ centred)
        out: FloatArray = vectors
        return out

    @cached_property
    def box(self) -> tuple[FloatArray, FloatArray]:
        """The mesh's box in its own frame, a micrometre wider each way: (lo, hi) (3,)."""
        vertices = np.asarray(self.mesh.vertices, dtype=np.float64)
        return vertices.min(axis=0) - 1e-3, vertices.max(axis=0) + 1e-3

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

    The rays are built in the part's frame, and only those that meet its box there are cast
    (a ray that misses the box misses the part): a long part seen side on fills a small share
    of the window its bounding sphere spans.
    """
    points, normals = [], []
    pose = np.asarray(pose, dtype=np.float64)
    to_part: FloatArray = np.asarray(np.linalg.inv(pose), dtype=np.float64)
    for cam in cameras:
        window = _window(part, pose, cam)
        if window is None:
            continue
        local_o = apply_pose(to_part, cam.centre[None])[0]
        to_local = np.ascontiguousarray(cam.world_to_camera[:3, :3] @ to_part[:3, :3].T)
        rays, local_d = _window_rays(_pixel_rays(cam.intrinsics), *window, stride, to_local,
                                     local_o, part.box[0], part.box[1])
        if not len(rays):
            continue
        cast = part.raycaster().cast_rays(o3d.core.Tensor.from_numpy(rays))
        t = cast["t_hit"].numpy()
        hit = np.isfinite(t)
        if not hit.any():
            continue
        if hidden_by is not None:  # (only the rays that meet the part are cast again)
            others, index = hidden_by
            rows = np.flatnonzero(hit)
            t_first, first = others.first(_rays(cam.centre, local_d[rows] @ pose[:3, :3].T))
            hit[rows] = (first == index) | (t[rows] <= t_first + 1.0)
            if not hit.any():
                continue
        pts, nrm = _facing_hits(t, cast["primitive_ids"].numpy(), hit, local_o, local_d,
                                part.facet_normals, pose)
        points.append(pts)
        normals.append(nrm)
    if not points:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(points), np.concatenate(normals)


def _rays(origin: FloatArray, dirs: FloatArray) -> npt.NDArray[np.float32]:
    """(n, 6) float32 rays for open3d's ray casting: one origin (3,), directions (n, 3)."""
    out = np.empty((len(dirs), 6), dtype=np.float32)
    out[:, :3] = origin
    out[:, 3:] = dirs
    return out


def _window(part: PartSurface, pose: FloatArray, cam: Camera
            ) -> tuple[int, int, int, int, FloatArray, float] | None:
    """The pixels over the part's projected bounding sphere (rows v0..v1, columns u0..u1)
    and the cone from the camera around the sphere (its axis in the camera's frame and the
    cosine of its half angle, -2: every ray of the window); None where the part is behind
    the camera or off the image."""
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
    # a ray meets the part only within the cone from the camera around its bounding sphere
    # (a tenth of a micrometre wider): the window's corners need no cast
    towards = apply_pose(cam.world_to_camera, centre[None])[0]
    distance = float(np.linalg.norm(towards))
    reach = part.radius + 1e-4
    cone = np.sqrt(1.0 - (reach / distance) ** 2) - 1e-9 if distance > reach else -2.0
    return v0, v1, u0, u1, towards / distance, float(cone)


@numba.njit(nogil=True, cache=True)
def _window_rays(table: Any, v0: int, v1: int, u0: int, u1: int,  # noqa: PLR0913
                 axis: Any, cone: float, stride: int, to_local: Any, origin: Any, lo: Any,
                 hi: Any) -> Any:
    """The rays (m, 6) float32, in the part's frame, of every ``stride``-th pixel of the
    window that lie within the cone and meet the part's box [lo, hi]; and their directions
    (m, 3) float64. ``table``: the pixels' unit rays in the camera's frame; ``to_local``:
    camera -> part rotation (a ray d goes to d @ to_local); ``origin``: the camera's centre
    in the part's frame."""
    rows = (v1 - v0) // stride + 1
    cols = (u1 - u0) // stride + 1
    dirs = np.empty((rows * cols, 3))
    m = 0
    for a in range(rows):
        for b in range(cols):
            v, u = v0 + a * stride, u0 + b * stride
            cx, cy, cz = table[v, u, 0], table[v, u, 1], table[v, u, 2]
            if cx * axis[0] + cy * axis[1] + cz * axis[2] < cone:
                continue
            d0 = cx * to_local[0, 0] + cy * to_local[1, 0] + cz * to_local[2, 0]
            d1 = cx * to_local[0, 1] + cy * to_local[1, 1] + cz * to_local[2, 1]
            d2 = cx * to_local[0, 2] + cy * to_local[1, 2] + cz * to_local[2, 2]
            if not _meets_box(origin, d0, d1, d2, lo, hi):
                continue
            dirs[m, 0], dirs[m, 1], dirs[m, 2] = d0, d1, d2
            m += 1
    rays = np.empty((m, 6), dtype=np.float32)
    for i in range(m):
        rays[i, 0], rays[i, 1], rays[i, 2] = origin[0], origin[1], origin[2]
        rays[i, 3], rays[i, 4], rays[i, 5] = dirs[i, 0], dirs[i, 1], dirs[i, 2]
    return rays, dirs[:m].copy()


@numba.njit(nogil=True, cache=True)
def _meets_box(origin: Any, d0: float, d1: float, d2: float, lo: Any, hi: Any) -> bool:
    """Whether the ray from ``origin`` along (d0, d1, d2) meets the box [lo, hi] ahead of it
    (the slab test)."""
    near, far = 0.0, np.inf
    for j, d in enumerate((d0, d1, d2)):
        if abs(d) < 1e-300:
            if origin[j] < lo[j] or origin[j] > hi[j]:
                return False
            continue
        t1, t2 = (lo[j] - origin[j]) / d, (hi[j] - origin[j]) / d
        near, far = max(near, min(t1, t2)), min(far, max(t1, t2))
    return near <= far


@numba.njit(nogil=True, cache=True)
def _facing_hits(t: Any, primitive: Any, hit: Any, origin: Any, dirs: Any,
                 facet_normals: Any, pose: Any) -> Any:
    """The hit points (n, 3) and outward normals (n, 3), world mm, of the rays marked ``hit``
    whose triangle faces the camera; the rays from ``origin`` along ``dirs`` (the part's frame)
    met the part at distance ``t`` on triangle ``primitive``."""
    n = 0
    for i in range(len(t)):
        n += hit[i]
    points, normals = np.empty((n, 3)), np.empty((n, 3))
    m = 0
    for i in range(len(t)):
        if not hit[i]:
            continue
        tri = primitive[i]
        nx, ny, nz = facet_normals[tri, 0], facet_normals[tri, 1], facet_normals[tri, 2]
        if nx * dirs[i, 0] + ny * dirs[i, 1] + nz * dirs[i, 2] >= 0:
            continue
        ti = float(t[i])
        px, py, pz = (origin[0] + dirs[i, 0] * ti, origin[1] + dirs[i, 1] * ti,
                      origin[2] + dirs[i, 2] * ti)
        for r in range(3):
            points[m, r] = pose[r, 0] * px + pose[r, 1] * py + pose[r, 2] * pz + pose[r, 3]
            normals[m, r] = pose[r, 0] * nx + pose[r, 1] * ny + pose[r, 2] * nz
        m += 1
    return points[:m].copy(), normals[:m].copy()


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
