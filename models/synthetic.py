"""Synthetic completion examples (boxes and cylinders) for tests, smoke runs and benchmarks.

Each solid is voxelized at n_out; each view observes the surface voxels that a camera looking
along one grid axis sees first, at n_in (a voxel of the coarse grid is occupied when any of its
fine voxels is). View 0 looks along +y, as the contract's first camera does; later views look
from the sides, behind, above and below. Depth images follow the contract.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from models.data import Example

# (axis, reversed): the camera looks along +axis when not reversed. View 0 looks along +y.
VIEW_DIRECTIONS = ((1, False), (0, False), (0, True), (1, True), (2, True), (2, False))

BoolGrid = npt.NDArray[np.bool_]


def box(n: int, centre: npt.ArrayLike, half: npt.ArrayLike) -> BoolGrid:
    """Voxels of an axis-aligned box, centre and half sizes in voxels: (n, n, n) bool."""
    c = (np.arange(n) + 0.5)[:, None]
    inside = np.abs(c - np.asarray(centre, dtype=float)) <= np.asarray(half, dtype=float)
    return inside[:, 0, None, None] & inside[None, :, 1, None] & inside[None, None, :, 2]


def cylinder(n: int, centre: npt.ArrayLike, radius: float, half_height: float) -> BoolGrid:
    """Voxels of a cylinder with its axis along z: (n, n, n) bool."""
    x, y, z = np.asarray(centre, dtype=float)
    c = np.arange(n) + 0.5
    disc = (c[:, None] - x) ** 2 + (c[None, :] - y) ** 2 <= radius**2
    return disc[:, :, None] & (np.abs(c - z) <= half_height)[None, None, :]


def observe(solid: BoolGrid, n_in: int, view: int) -> BoolGrid:
    """The coarse voxels of ``solid`` a camera looking along view ``view``'s axis sees first."""
    f = solid.shape[0] // n_in
    coarse = solid.reshape(n_in, f, n_in, f, n_in, f).any(axis=(1, 3, 5))
    axis, rev = VIEW_DIRECTIONS[view % len(VIEW_DIRECTIONS)]
    grid = np.flip(coarse, axis) if rev else coarse
    first = grid & (np.cumsum(grid, axis=axis) == 1)
    return np.flip(first, axis) if rev else first


def depth_image(observed: BoolGrid) -> npt.NDArray[np.float32]:
    """The contract's (2, 2n, 2n) depth view of one view's observed grid, indexed (x, z)."""
    n = observed.shape[0]
    seen = observed.any(axis=1)  # (x, z)
    dist = np.where(seen, (observed.argmax(axis=1) + 0.5) / n, 1.0)
    image = np.stack([dist, seen]).astype(np.float32)
    return image.repeat(2, axis=1).repeat(2, axis=2)


def example(solid: BoolGrid, n_in: int, n_views: int, meta: dict[str, object]) -> Example:
    """An example of ``solid`` seen from views 0..n_views-1."""
    inputs = np.stack([observe(solid, n_in, v) for v in range(n_views)])
    depth = np.stack([depth_image(obs) for obs in inputs])
    return Example(inputs, solid, depth, meta)


def synthetic_examples(count: int, n_in: int = 32, n_out: int = 64, n_views: int = 3,
                       seed: int = 0) -> list[Example]:
    """``count`` random boxes and cylinders (alternating), each seen from ``n_views`` views."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        centre = n_out / 2 + rng.uniform(-0.1, 0.1, 3) * n_out
        if i % 2 == 0:
            solid = box(n_out, centre, rng.uniform(0.12, 0.35, 3) * n_out)
            kind = "box"
        else:
            r, h = rng.uniform(0.12, 0.35) * n_out, rng.uniform(0.15, 0.35) * n_out
            solid = cylinder(n_out, centre, r, h)
            kind = "cylinder"
        out.append(example(solid, n_in, n_views, {"part_id": f"{kind}-{i}", "category": kind}))
    return out
