"""Solid voxel occupancy of parts on cubic grids, and grids from points, and their IoU.

The completion models and the IoU metric of the paper work on n^3 occupancy grids (64^3 in,
256^3 out). A part's truth grid is a cube centred on its bounding box and never stretched (see
``VoxelGrid``); partial views of the same part are binned onto that same grid with
``points_to_grid`` so the two compare voxel for voxel.

Occupancy is decided by ray parity. A grid's voxel centres lie on n^2 lines along each grid
axis, so one ray per line (open3d's ``list_intersections``) decides a whole column: a centre
is inside when an odd number of the line's crossings lie before it. Each voxel is decided from
the lines of two axes; where they disagree, or a line is not clean (an odd count of crossings,
a crossing on a triangle's edge or grazing it, a centre on the surface), the voxel is asked of
open3d's ``RaycastingScene.compute_occupancy`` at its own centre, as every voxel once was.
On a closed mesh the answer is the same, at about a twentieth of the cost; on a mesh with holes
it errs less than one ray per voxel does (a line through a hole is unsure, or outvoted).
Voxels whose ray provably passes beside the mesh's box are outside (see ``_rays_may_hit_box``),
and all sizes of one mesh share one scene, so its BVH is built once.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import open3d as o3d

from cadio.errors import GeometryError
from cadio.records import FloatArray, Mesh, VoxelGrid

log = logging.getLogger(__name__)

BoolArray = npt.NDArray[np.bool_]

# Query points per occupancy call: ~12 MB of float32 points; bounds memory at 256^3.
CHUNK_POINTS = 1 << 20
# Rays per query point (odd, majority vote). Three rays cost 2.5x and changed no voxel on the
# real parts tried; raise it if grazing rays ever flip voxels.
OCCUPANCY_RAYS = 1
# open3d casts each occupancy ray from the query point along (1, 1, 1), each component
# perturbed by less than 1e-3 (open3d 0.17-0.20, VoteInsideOutside; the same rays for every
# point of a call, so asking fewer points changes no answer). A voxel whose ray misses the
# mesh's box for every direction in this wider range crosses no triangle: it is outside.
# tests/test_voxels.py checks the shortcut against asking open3d for every voxel.
_RAY_DIRECTION_RANGE = (0.998, 1.002)
# A line's crossing this close to a triangle's edge (barycentric), or at this cosine or less
# between the line and the triangle's normal, makes the line's parity unsure; so does a
# crossing this close (in voxels) to a voxel's centre for that voxel.
_EDGE_EPS = 1e-4
_GRAZING_COS = 1e-4
_ON_SURFACE_EPS = 1e-3
# The mesh's box is padded by this fraction of its size (plus float32 rounding) for that test.
_RAY_BOX_PAD = 1e-3


def grid_transform(
    bbox_min: FloatArray, bbox_max: FloatArray, n: int, margin: float = 0.05
) -> FloatArray:
    """The grid-to-part transform of an n^3 cube around a bounding box.

    Args:
        bbox_min, bbox_max: (3,) mm, the part's axis-aligned box.
        n: voxels along each axis.
        margin: the cube's side is the largest extent times (1 + margin).

    Returns:
        (4, 4) float64 mapping homogeneous (i, j, k, 1) to the centre of voxel (i, j, k), mm.

    Raises:
        ValueError: when n < 1, margin < 0, or the box is empty or degenerate.
    """
    lo = np.asarray(bbox_min, dtype=np.float64).reshape(3)
    hi = np.asarray(bbox_max, dtype=np.float64).reshape(3)
    if n < 1 or margin < 0:
        raise ValueError(f"need n >= 1 and margin >= 0, got n={n}, margin={margin}")
    extent = float(np.max(hi - lo))
    if not np.isfinite(extent) or extent <= 0:
        raise ValueError(f"degenerate bounding box {lo.tolist()} .. {hi.tolist()}")
    side = extent * (1.0 + margin)
    size = side / n
    transform = np.diag([size, size, size, 1.0])
    transform[:3, 3] = (lo + hi) / 2.0 - side / 2.0 + size / 2.0
    return transform


def voxel_centres(grid_to_part: FloatArray, n: int, i_start: int = 0,
                  i_stop: int | None = None) -> npt.NDArray[np.float32]:
    """Centres of voxels [i_start:i_stop, :, :] in part coordinates.

    Args:
        grid_to_part: (4, 4) from ``grid_transform``.
        n: voxels along each axis.
        i_start, i_stop: the slab of x indices (all of them by default).

    Returns:
        (i_stop - i_start, n, n, 3) float32 mm (open3d's query type), indexed like the
        occupancy.
    """
    i_stop = n if i_stop is None else i_stop
    return _centres(grid_to_part, np.arange(i_start, i_stop)[:, None, None],
                    np.arange(n)[None, :, None], np.arange(n)[None, None, :])


def _centres(grid_to_part: FloatArray, i: npt.NDArray[np.int64], j: npt.NDArray[np.int64],
             k: npt.NDArray[np.int64]) -> npt.NDArray[np.float32]:
    """Centres (..., 3) float32 of the voxels at indices i, j, k (arrays broadcast together).

    The same float32 operations in the same order for any choice of indices, so a centre does
    not depend on which others are computed with it.
    """
    t = np.asarray(grid_to_part, dtype=np.float32)
    fi, fj, fk = (np.asarray(a, dtype=np.float32)[..., None] for a in (i, j, k))
    # Broadcast sums: about 10x faster than a (m, 4) @ (4, 4) product on 16.7 M centres.
    return np.asarray(t[:3, 3] + fi * t[:3, 0] + fj * t[:3, 1] + fk * t[:3, 2], dtype=np.float32)


def voxelize(mesh: Mesh, n: int, margin: float = 0.05) -> VoxelGrid:
    """Solid occupancy of a closed mesh on an n^3 grid around its bounding box.

    Args:
        mesh: closed triangle mesh, mm (small holes are tolerated).
        n: voxels along each axis (64 and 256 are the sizes used).
        margin: see ``grid_transform``.

    Returns:
        VoxelGrid: occupancy (n, n, n) bool, True where the voxel centre is inside the mesh.

    Raises:
        GeometryError: when the mesh has no triangles.
        ValueError: on a bad n or margin.
    """
    return voxelize_sizes(mesh, (n,), margin)[0]


def voxelize_sizes(mesh: Mesh, sizes: Sequence[int], margin: float = 0.05) -> list[VoxelGrid]:
    """``voxelize`` at several sizes, sharing one ray-casting scene (built once).

    Args:
        mesh: closed triangle mesh, mm (small holes are tolerated).
        sizes: voxels along each axis, one grid per entry.
        margin: see ``grid_transform``.

    Returns:
        One VoxelGrid per size, in order.

    Raises:
        GeometryError: when the mesh has no triangles.
        ValueError: on a bad size or margin.
    """
    scene = _MeshScene(mesh)
    transforms = [grid_transform(scene.lo, scene.hi, n, margin) for n in sizes]
    return [VoxelGrid(occupancy=scene.occupancy(t, n), grid_to_part=t)
            for t, n in zip(transforms, sizes, strict=True)]


def occupancy_in(mesh: Mesh, grid_to_part: FloatArray, n: int) -> BoolArray:
    """Solid occupancy of a closed mesh at the voxel centres of any n^3 grid.

    Args:
        mesh: closed triangle mesh, mm, part coordinates.
        grid_to_part: (4, 4) affine map of (i, j, k, 1) to voxel centres in part coordinates
            (mm); it may rotate and scale, e.g. a grid placed by a camera's view.
        n: voxels along each axis.

    Returns:
        (n, n, n) bool, True where the voxel centre is inside the mesh.

    Raises:
        GeometryError: when the mesh has no triangles.
    """
    return _MeshScene(mesh).occupancy(grid_to_part, n)


class _MeshScene:
    """open3d's ray-casting scene of one mesh (its BVH built once) and the mesh's box, mm."""

    def __init__(self, mesh: Mesh) -> None:
        if len(mesh.triangles) == 0:
            raise GeometryError("voxelize", "mesh has no triangles")
        self.lo, self.hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        # float64 corners of each triangle: the grazing test of the lines' crossings
        self.triangles = np.asarray(mesh.vertices, dtype=np.float64)[mesh.triangles]
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(mesh.triangles, dtype=np.uint32)),
        )

    def occupancy(self, grid_to_part: FloatArray, n: int) -> BoolArray:
        """(n, n, n) occupancy of the voxel centres: by the parity along the lines of two grid
        axes where both are sure and agree, by open3d at the centre elsewhere (see the module
        doc); sure misses of the box are not asked."""
        inside_i, sure_i = self._line_parity(grid_to_part, n, 0)
        inside_j, sure_j = self._line_parity(grid_to_part, n, 1)
        sure = sure_i & sure_j & (inside_i == inside_j)
        occupancy: BoolArray = np.ascontiguousarray(inside_i & sure)
        del inside_j, sure_i, sure_j
        i, j, k = np.nonzero(~sure)
        ask = _rays_may_hit_box(grid_to_part, (i, j, k), self.lo, self.hi)
        i, j, k = i[ask], j[ask], k[ask]
        for start in range(0, len(i), CHUNK_POINTS):
            at = slice(start, start + CHUNK_POINTS)
            points = _centres(grid_to_part, i[at], j[at], k[at])  # only the voxels asked
            inside = self.scene.compute_occupancy(o3d.core.Tensor.from_numpy(points),
                                                  nsamples=OCCUPANCY_RAYS)
            occupancy[i[at], j[at], k[at]] = inside.numpy().astype(bool)
        return occupancy

    def _line_parity(self, grid_to_part: FloatArray, n: int, axis: int
                     ) -> tuple[BoolArray, BoolArray]:
        """Occupancy by crossing parity along the grid lines of one axis, and where it is sure.

        One ray per line, from well before the mesh's box, with the grid's step along
        ``axis`` as direction, so a crossing's t minus the start's offset is its position in
        voxel indices. A line is unsure when its crossings are odd in number, or one is within
        ``_EDGE_EPS`` of a triangle's edge (barycentric) or grazes its triangle; a voxel is
        unsure when a crossing lies within ``_ON_SURFACE_EPS`` voxels of its centre.

        Returns:
            (inside, sure), each (n, n, n) bool indexed (i, j, k).
        """
        others = [b for b in range(3) if b != axis]
        step = grid_to_part[:3, axis]
        a, b = np.meshgrid(np.arange(n, dtype=np.float64), np.arange(n, dtype=np.float64),
                           indexing="ij")
        starts = (grid_to_part[:3, 3] + a[..., None] * grid_to_part[:3, others[0]]
                  + b[..., None] * grid_to_part[:3, others[1]]).reshape(-1, 3)
        centre, reach = (self.lo + self.hi) / 2.0, float(np.linalg.norm(self.hi - self.lo))
        length = float(np.linalg.norm(step))
        offset = float(np.ceil((np.linalg.norm(starts - centre, axis=1).max() + reach)
                               / length)) + 1.0
        rays = np.empty((n * n, 6), dtype=np.float32)
        rays[:, :3] = starts - offset * step
        rays[:, 3:] = step
        hits = self.scene.list_intersections(o3d.core.Tensor.from_numpy(rays))
        line = hits["ray_ids"].numpy().astype(np.int64)
        pos = hits["t_hit"].numpy().astype(np.float64) - offset
        uv = hits["primitive_uvs"].numpy()
        triangles = self.triangles[hits["primitive_ids"].numpy().astype(np.int64)]
        normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        cosine = np.abs(normals @ step) / (np.linalg.norm(normals, axis=1) * length + 1e-300)
        edge = np.minimum(np.minimum(uv[:, 0], uv[:, 1]), 1.0 - uv[:, 0] - uv[:, 1])
        bad = np.bincount(line, minlength=n * n) % 2 == 1
        bad[line[(edge < _EDGE_EPS) | (cosine < _GRAZING_COS)]] = True
        # Each crossing flips the voxels after it: the parity is the running xor of the flips,
        # row after row of (index along the axis, line) (numpy's accumulate along the first
        # axis is 40x slower than this loop of n vector xors).
        inside = np.zeros((n + 1, n * n), dtype=bool)
        np.logical_xor.at(inside, (np.clip(np.floor(pos) + 1, 0, n).astype(np.int64), line),
                          True)
        for row in range(1, n):
            np.logical_xor(inside[row - 1], inside[row], out=inside[row])
        inside = inside[:n]
        sure = np.repeat(~bad[None, :], n, axis=0)
        nearest = np.rint(pos)
        close = (np.abs(pos - nearest) < _ON_SURFACE_EPS) & (nearest >= 0) & (nearest < n)
        sure[nearest[close].astype(np.int64), line[close]] = False
        # (along axis, line a, line b) -> (i, j, k)
        return (np.moveaxis(inside.reshape(n, n, n), 0, axis),
                np.moveaxis(sure.reshape(n, n, n), 0, axis))


def _rays_may_hit_box(grid_to_part: FloatArray, ijk: tuple[npt.NDArray[np.int64], ...],
                      lo: FloatArray, hi: FloatArray) -> BoolArray:
    """Whether the occupancy ray of each voxel centre asked may meet the (padded) box [lo, hi].

    The ray p + t d (t >= 0, every d_i in ``_RAY_DIRECTION_RANGE``) is inside the box on axis
    i for t in [(lo_i - p_i) / d_i, (hi_i - p_i) / d_i]; it surely misses when the latest entry
    (at t >= 0) comes after the earliest exit whatever d is, which covers a start beyond the
    box on some axis (a negative exit).

    Args:
        grid_to_part: (4, 4) the grid's transform, mm.
        ijk: the voxels' indices i, j, k (arrays of one shape).
        lo, hi: (3,) the box, mm.

    Returns:
        bool, of the indices' shape.
    """
    d_min, d_max = _RAY_DIRECTION_RANGE
    # The pad also covers the float32 rounding of the centres open3d is given.
    pad = _RAY_BOX_PAD * float(np.max(hi - lo)) + 1e-6 * float(np.max(np.abs([lo, hi])))
    entry: FloatArray | float = 0.0
    exit_: FloatArray | float = np.inf
    for c in range(3):
        coord = grid_to_part[c, 3] + sum(ijk[a] * grid_to_part[c, a] for a in range(3))
        entry = np.maximum(entry, lo[c] - pad - coord)
        exit_ = np.minimum(exit_, hi[c] + pad - coord)
    return np.asarray(np.asarray(entry) * (d_min / d_max) <= np.asarray(exit_))


def points_to_grid(points: FloatArray, grid_to_part: FloatArray, n: int) -> BoolArray:
    """Mark the voxels of an existing grid that contain at least one point.

    Args:
        points: (m, 3) mm in part coordinates (e.g. a back-projected partial view).
        grid_to_part: (4, 4), the grid of the same part's truth ``VoxelGrid``.
        n: voxels along each axis of that grid.

    Returns:
        (n, n, n) bool; points outside the cube are ignored.

    Raises:
        ValueError: when ``points`` is not (m, 3).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (m, 3), got {pts.shape}")
    part_to_grid = np.linalg.inv(grid_to_part)
    ijk = np.floor(pts @ part_to_grid[:3, :3].T + part_to_grid[:3, 3] + 0.5).astype(np.int64)
    keep = np.all((ijk >= 0) & (ijk < n), axis=1)
    grid = np.zeros((n, n, n), dtype=bool)
    grid[ijk[keep, 0], ijk[keep, 1], ijk[keep, 2]] = True
    return grid


def iou(a: BoolArray, b: BoolArray) -> float:
    """Intersection over union of two occupancy grids.

    Args:
        a, b: boolean grids of the same shape.

    Returns:
        |a and b| / |a or b| in [0, 1]; 1.0 when both are empty (they agree everywhere).

    Raises:
        ValueError: when the shapes differ.
    """
    if a.shape != b.shape:
        raise ValueError(f"grids differ in shape: {a.shape} vs {b.shape}")
    union = int(np.count_nonzero(a | b))
    if union == 0:
        return 1.0
    return float(np.count_nonzero(a & b)) / union
