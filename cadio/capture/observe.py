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

In either grid, ``view_states`` gives each voxel one of three states from one view (DESIGN.md,
"Learning inputs"): seen surface (the part's own pixels meet the voxel), seen free (the camera's
ray passed through it, or it lies under the support plane the view saw) or unknown (behind a
surface, hidden by another instance, outside the image). The states come from projecting every
voxel centre into the depth image, so they do not depend on how many pixels a voxel catches: a
small part far away and a large one close by give the same kind of grid. ``depth_view``
renders the part's seen surface as a 2D depth image along +y (the input of the ``r2n2``
baseline) and ``carve`` is the ``carve`` baseline (no learning: what lies behind the observed
surface along each camera ray, carved by every view). The truth is voxelized into the same grid
by ``truth_occupancy``, for the loss and the score only; ``cadio.capture.examples`` checks that
no truth reaches the inputs.

Lengths are metres in the world frame of the capture (the scene scaled by ``scale_m_per_mm``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from cadio.cad.voxels import occupancy_in
from cadio.records import CameraIntrinsics, FloatArray, Mesh
from cadio.truth.relations import view_frame

BoolGrid = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class GridRule:
    """The one rule that places the observed-protocol grid from the observed points.

    In the first view's observer frame, the observed points span [lo, hi]. Across the view
    (x) and vertically (z) the part is taken to span what was seen, except on a side where its
    silhouette meets a nearer instance (an occluder, ``occluded_sides``): there the part may go
    on into the unknown space the occluder hides, so the box grows by ``occluded_extend`` times
    the largest seen extent on that side (never below the support plane the view saw). Along
    the view (y) the camera sees only the front: the part is assumed to reach ``depth_prior``
    times its largest seen extent behind the nearest observed point (a part is about as deep as
    it is wide), or what was seen, if more. The cube is centred on that estimated box and its
    side is the box's largest extent times ``1 + margin``, so the completed shape has room.
    """

    depth_prior: float = 1.0
    margin: float = 0.15
    # How far an occluded side may go on, times the largest seen extent: half of what was seen
    # is hidden at most for a part that still shows enough points to be completed.
    occluded_extend: float = 0.5
    # A silhouette side counts as occluded when at least this share of its border pixels (and
    # ``occluded_min_px`` of them) touch a nearer instance.
    occluded_share: float = 0.15
    occluded_min_px: int = 3


SURFACE, FREE = 0, 1  # channels of a state grid; a voxel in neither is unknown
N_STATES = 2
# Image sides of a silhouette, in the order ``occluded_sides`` reports them, and the observer
# axis (x right, z up) and sign each one faces: image u grows to the right, v downwards.
SIDES = ("left", "right", "top", "bottom")
_SIDE_AXIS = {"left": (0, -1), "right": (0, 1), "top": (2, 1), "bottom": (2, -1)}


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
               rule: GridRule = GridRule(), occluded: tuple[str, ...] = (),
               support: tuple[FloatArray, float] | None = None) -> CubeGrid:
    """The observed-protocol cube of a part from its observed points and the first camera.

    Args:
        points_world: (m, 3) observed points of the part in all views given, world metres.
        world_to_camera: (4, 4) the first view's camera (its observer frame orients the cube).
        rule: the placement rule.
        occluded: sides of the first view's silhouette hidden by a nearer instance
            (``occluded_sides``); the box goes on into the unknown space there.
        support: the support plane the first view saw (unit normal up, offset; world metres):
            an occluded bottom side does not go below it.

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
    grow = rule.occluded_extend * float(np.max(seen))
    box_lo, box_hi = lo.copy(), hi.copy()
    for hidden in occluded:
        axis, sign = _SIDE_AXIS[hidden]
        if sign > 0:
            box_hi[axis] += grow
        else:
            box_lo[axis] -= grow
    if "bottom" in occluded and support is not None:
        box_lo[2] = max(box_lo[2], min(lo[2], _support_height(support, rot, (lo + hi) / 2)))
    depth = max(seen[1], rule.depth_prior * max(box_hi[0] - box_lo[0], box_hi[2] - box_lo[2]))
    box_hi[1] = lo[1] + depth
    side = max(float(np.max(box_hi - box_lo)), 1e-6) * (1.0 + rule.margin)
    centre = (box_lo + box_hi) / 2
    return CubeGrid(rotation=rot, corner=rot @ (centre - side / 2), side=side)


def _support_height(support: tuple[FloatArray, float], rot: FloatArray,
                    at: FloatArray) -> float:
    """Observer-frame height of the support plane under the observer-frame point ``at``."""
    normal, offset = support
    n_local = rot.T @ np.asarray(normal, dtype=np.float64)
    if abs(n_local[2]) < 1e-6:
        return -math.inf
    # n . (x, y, z) = offset, solved for z at the point's x and y.
    return float((offset - n_local[0] * at[0] - n_local[1] * at[1]) / n_local[2])


def occluded_sides(view: ViewEvidence, rule: GridRule = GridRule()) -> tuple[str, ...]:
    """Sides of the part's outer silhouette (``SIDES``) that a nearer instance hides.

    On each image row the part's leftmost and rightmost pixels, on each column its topmost
    and bottommost, are its outer border on that side (an instance in front of the part's
    middle cuts holes in its mask, which say nothing of how far the part reaches). Such a
    border pixel is occluded when its outward neighbour belongs to another instance
    (``view.others``) nearer the camera. A side counts when enough of its border pixels are
    (``GridRule.occluded_share``, ``occluded_min_px``).
    """
    if view.others is None or not view.mask.any():
        return ()
    depth = np.nan_to_num(view.depth, nan=0.0)
    out = []
    for side in SIDES:
        # Turn the images so that this side's outward direction is towards column 0.
        mask, d, others = (_outward(m, side) for m in (view.mask, depth, view.others))
        rows = np.flatnonzero(mask.any(axis=1))
        first = mask[rows].argmax(axis=1)  # the outermost pixel of each row on this side
        inside = first > 0
        r, c = rows[inside], first[inside]
        nb_depth = d[r, c - 1]
        hidden = others[r, c - 1] & (nb_depth > 0) & (nb_depth < d[r, c])
        if hidden.sum() >= max(rule.occluded_min_px, rule.occluded_share * len(rows)):
            out.append(side)
    return tuple(out)


def _outward(image: npt.NDArray[Any], side: str) -> npt.NDArray[Any]:
    """``image`` turned so that ``side`` of the picture faces column 0."""
    turned = image.T if side in ("top", "bottom") else image
    return turned[:, ::-1] if side in ("right", "bottom") else turned


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


@dataclass(frozen=True)
class ViewEvidence:
    """One view as the inputs and the carve baseline need it: depth (h, w) metres (0 = no
    return), the part's pixels (h, w) bool (segmented), the camera, the support plane the view
    saw (unit normal pointing up (3,), offset d: n . p = d, world metres; None when it saw
    none) and the pixels of the other instances in view (h, w) bool (None when unknown)."""

    depth: npt.NDArray[np.float32]
    mask: npt.NDArray[np.bool_]
    intrinsics: CameraIntrinsics
    world_to_camera: FloatArray
    support: tuple[FloatArray, float] | None = None
    others: npt.NDArray[np.bool_] | None = None


def view_states(view: ViewEvidence, points_world: FloatArray, grid: CubeGrid,
                n: int, grids: PartGrids | None = None) -> BoolGrid:
    """(2, n, n, n) bool: the seen-surface and seen-free voxels of one view (``SURFACE``,
    ``FREE``); a voxel in neither is unknown.

    Every voxel centre is projected into the view. It is *free* when the pixel has a return
    and the centre lies in front of it by more than half a voxel diagonal (the ray passed
    through), or when it lies under the support plane the view saw. It is *surface* when the
    pixel is the part's and the return lies within half a diagonal of the centre, or when one
    of the part's observed points falls in it (a voxel smaller than a pixel is met by its
    centre's pixel alone; one larger than a pixel by the points). Surface wins over free.
    ``grids``: where one part's examples are built, the projections they share.
    """
    return _cast(view, grid, n, grids).states(points_world)


class _ViewCast:
    """One view's projection of a grid's voxel centres: what ``view_states`` and ``carve``
    read, computed once for both (``_cast_kernel``: one compiled pass over the centres)."""

    def __init__(self, view: ViewEvidence, grid: CubeGrid, n: int) -> None:
        self.view, self.grid, self.n = view, grid, n
        k = view.intrinsics
        slack = np.float32(0.5 * np.sqrt(3.0) * grid.voxel_m(n))
        normal, offset = view.support if view.support is not None else (np.zeros(3), np.nan)
        plane = np.array([*normal, np.float32(offset) - slack], dtype=np.float32)
        self.surface, self.free, self._behind = _cast_kernel(
            np.asarray(grid.grid_to_world(n), dtype=np.float32), n,
            np.ascontiguousarray(np.asarray(view.world_to_camera, dtype=np.float32)[:3]),
            np.array([k.fx, k.fy, k.cx + 0.5, k.cy + 0.5], dtype=np.float32),
            np.ascontiguousarray(view.depth, dtype=np.float32), np.ascontiguousarray(view.mask),
            slack, plane)
        self._states: tuple[FloatArray, BoolGrid] | None = None

    def states(self, points_world: FloatArray) -> BoolGrid:
        if self._states is not None and self._states[0] is points_world:
            return self._states[1]  # a view's own points, asked again: the same states
        n = self.n
        surface = self.surface.reshape(n, n, n) | observed_occupancy(points_world, self.grid, n)
        out = np.stack([surface, self.free.reshape(n, n, n) & ~surface])
        out.flags.writeable = False  # shared by every example that asks again
        self._states = (points_world, out)
        return out

    def behind(self) -> npt.NDArray[np.bool_]:
        """(n^3,) centres at or behind the part's surface on the part's own pixels."""
        return self._behind


@numba.njit(nogil=True, cache=True)
def _cast_kernel(g2w: npt.NDArray[np.float32], n: int, cam: npt.NDArray[np.float32],
                 pinhole: npt.NDArray[np.float32], depth: npt.NDArray[np.float32],
                 mask: npt.NDArray[np.bool_], slack: np.float32, plane: npt.NDArray[np.float32]
                 ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_],
                            npt.NDArray[np.bool_]]:  # pragma: no cover
    """Every voxel centre of an n^3 grid (``g2w``: index -> world) projected into one view
    (``cam``: world -> camera, (3, 4); ``pinhole``: fx, fy, cx + 0.5, cy + 0.5).

    Per centre, in float32 and in the order of the numpy passes it replaces (``voxel_centres``,
    the camera transform, the pinhole): the pixel it falls on, the return there (0 outside the
    image, for no return or NaN) and the part's mask there (``depth``, ``mask``: (h, w)).
    Returns, (n^3,) each: *surface* (a return on the part's pixel within ``slack`` of the
    centre), *free* (a return beyond the centre by more than ``slack``, or the centre under the
    support plane n . p = d by more than ``slack``: ``plane`` is (n, d - slack), d NaN for no
    plane) and *behind* (the part's pixel, the centre not in front of its return by more than
    ``slack``). numpy made a dozen temporaries of 262k points per view and grid: the capture
    stage spent most of its time in them.
    """
    height, width = depth.shape
    total = n * n * n
    surface = np.zeros(total, dtype=np.bool_)
    free = np.zeros(total, dtype=np.bool_)
    behind = np.zeros(total, dtype=np.bool_)
    for idx in range(total):
        fi = np.float32(idx // (n * n))
        fj = np.float32((idx // n) % n)
        fk = np.float32(idx % n)
        c0 = g2w[0, 3] + fi * g2w[0, 0] + fj * g2w[0, 1] + fk * g2w[0, 2]
        c1 = g2w[1, 3] + fi * g2w[1, 0] + fj * g2w[1, 1] + fk * g2w[1, 2]
        c2 = g2w[2, 3] + fi * g2w[2, 0] + fj * g2w[2, 1] + fk * g2w[2, 2]
        free[idx] = c0 * plane[0] + c1 * plane[1] + c2 * plane[2] < plane[3]
        z = c0 * cam[2, 0] + c1 * cam[2, 1] + c2 * cam[2, 2] + cam[2, 3]
        if not z > 1e-9:
            continue
        inv = np.float32(1.0) / z
        x = c0 * cam[0, 0] + c1 * cam[0, 1] + c2 * cam[0, 2] + cam[0, 3]
        y = c0 * cam[1, 0] + c1 * cam[1, 1] + c2 * cam[1, 2] + cam[1, 3]
        u = math.floor(x * inv * pinhole[0] + pinhole[2])
        v = math.floor(y * inv * pinhole[1] + pinhole[3])
        if u < 0 or u >= width or v < 0 or v >= height:
            continue
        at = depth[v, u]
        if not at == at:  # NaN: no return
            at = np.float32(0.0)
        front = z < at - slack
        free[idx] = free[idx] or (at > 0 and front)
        if mask[v, u]:
            surface[idx] = at > 0 and abs(z - at) <= slack
            behind[idx] = not front
    return surface, free, behind


def states_and_carve(views: Sequence[ViewEvidence], points: Sequence[FloatArray],
                     grid: CubeGrid, n: int, grids: PartGrids | None = None
                     ) -> tuple[list[BoolGrid], BoolGrid]:
    """Each view's ``view_states`` and the views' ``carve``, from one projection per view."""
    casts = [_cast(v, grid, n, grids) for v in views]
    return [c.states(p) for c, p in zip(casts, points, strict=True)], _carved(casts, n)


class PartGrids:
    """What one part's examples share, computed once while they are built: a view's
    projection into a grid (and its states there), the oracle-box grid, and the truth in a grid.

    Every oracle-box example of a part lies in the part's one truth grid, so each view is
    projected into it once, not once per sequence that holds it, and the truth is voxelized
    once, not once per example; the results are the same arrays. Keyed by the objects
    themselves (kept here, so that their ids stay theirs): build one per part.
    """

    def __init__(self) -> None:
        self._casts: dict[tuple[int, int, int], tuple[ViewEvidence, CubeGrid, _ViewCast]] = {}
        self._oracle: CubeGrid | None = None
        self._truths: dict[tuple[int, int], tuple[CubeGrid, BoolGrid]] = {}

    def cast(self, view: ViewEvidence, grid: CubeGrid, n: int) -> _ViewCast:
        key = (id(view), id(grid), n)
        if key not in self._casts:
            self._casts[key] = (view, grid, _ViewCast(view, grid, n))
        return self._casts[key][2]

    def oracle(self, mesh: Mesh, part_to_world: FloatArray, margin: float) -> CubeGrid:
        """``oracle_grid`` of the part (one part per instance of this class)."""
        if self._oracle is None:
            self._oracle = oracle_grid(mesh, part_to_world, margin)
        return self._oracle

    def truth(self, mesh: Mesh, part_to_world: FloatArray, grid: CubeGrid, n: int) -> BoolGrid:
        """``truth_occupancy`` of the part in ``grid`` (read-only: examples share it)."""
        key = (id(grid), n)
        if key not in self._truths:
            target = truth_occupancy(mesh, part_to_world, grid, n)
            target.flags.writeable = False
            self._truths[key] = (grid, target)
        return self._truths[key][1]


def _cast(view: ViewEvidence, grid: CubeGrid, n: int, grids: PartGrids | None) -> _ViewCast:
    return grids.cast(view, grid, n) if grids is not None else _ViewCast(view, grid, n)


def union_states(states: BoolGrid) -> BoolGrid:
    """(2, n, n, n): the states of several views (V, 2, n, n, n) merged. Surface where any
    view saw the part's surface; free where any view saw through and none saw surface."""
    surface = states[:, SURFACE].any(axis=0)
    return np.stack([surface, states[:, FREE].any(axis=0) & ~surface])


def depth_view(surface: BoolGrid) -> npt.NDArray[np.float32]:
    """(2, d, d) float32: a seen-surface grid (d, d, d) as a depth image seen along +y.

    Channel 0: distance along +y of the nearest surface voxel in each (x, z) column, as a
    fraction of the side (1 where nothing was seen); channel 1: 1 where something was seen.
    Indexed [x, z].
    """
    d = surface.shape[1]
    hit = surface.any(axis=1)  # (d, d) over x, z
    first = np.argmax(surface, axis=1).astype(np.float32)  # first True along y
    depth = np.where(hit, (first + 0.5) / d, 1.0).astype(np.float32)
    return np.stack([depth, hit.astype(np.float32)])


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
    return _carved([_ViewCast(v, grid, n) for v in views], n)


def _carved(casts: Sequence[_ViewCast], n: int) -> BoolGrid:
    if not casts:
        return np.zeros((n, n, n), dtype=bool)
    free = np.zeros(n**3, dtype=bool)
    behind = np.zeros(n**3, dtype=bool)
    for cast in casts:
        free |= cast.free
        behind |= cast.behind()
    return (behind & ~free).reshape(n, n, n)


def truth_occupancy(mesh: Mesh, part_to_world: FloatArray, grid: CubeGrid, n: int) -> BoolGrid:
    """The part's solid in the cube (for the loss and the score only: it uses the true pose).

    Args:
        mesh: the part, mm, part coordinates. part_to_world: (4, 4) part mm -> world metres.
    """
    grid_to_part = np.linalg.inv(np.asarray(part_to_world, dtype=np.float64)) @ (
        grid.grid_to_world(n))
    return occupancy_in(mesh, grid_to_part, n)
