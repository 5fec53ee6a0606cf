"""The per-pixel work of a render: camera rays, the tests that choose which rays open3d casts
(the scene's box, the image outline of the parts' box, the support plane in closed form), and
shading, as compiled loops (numba) that release the GIL.

``cadio.camera.render`` stages a scene and drives these per view; as numpy passes over 307k
pixels this work cost about as much as ``cast_rays`` itself, and could not run while
``cast_rays`` (which holds the GIL) cast the next view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from cadio.camera.noise import measure_depth
from cadio.records import CameraIntrinsics, FloatArray

MISS = -1  # open3d's geometry id for a ray that hits nothing, 0xFFFFFFFF, read as int32
# What became of a pixel's ray: nothing in its way (a miss), cast by open3d, or meeting the
# support plane in closed form.
NOT_CAST, CAST, ON_TABLE = 0, 1, 2
# Shading goes through a table of (geometry, light level) -> sRGB: per-pixel float colour
# arithmetic and np.power cost more than the ray cast itself.
LEVELS = 1024


@dataclass(frozen=True)
class PixelGrid:
    """Per-pixel camera-frame ray directions (x/z, y/z, z = 1), flattened row-major, and the
    inverse length of each, precomputed once per camera."""

    x: npt.NDArray[np.float32]
    y: npt.NDArray[np.float32]
    inv_norm: npt.NDArray[np.float32]


def pixel_directions(k: CameraIntrinsics) -> npt.NDArray[np.float64]:
    """(h*w, 3) camera-frame ray directions with z = 1, row-major pixel order."""
    u, v = np.meshgrid(np.arange(k.width, dtype=np.float64), np.arange(k.height, dtype=np.float64))
    d = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1)
    return d.reshape(-1, 3)


def pixel_grid(k: CameraIntrinsics) -> PixelGrid:
    """The camera's per-pixel directions, as ``camera_rays`` takes them."""
    d = pixel_directions(k)
    return PixelGrid(d[:, 0].astype(np.float32), d[:, 1].astype(np.float32),
                     (1.0 / np.linalg.norm(d, axis=1)).astype(np.float32))


def camera_rays(w2c: FloatArray, px: PixelGrid) -> npt.NDArray[np.float32]:
    """(n, 6) float32 rays: camera centre and world directions whose camera z is 1, so a
    ray's hit distance is the pixel's z-depth in metres."""
    rays = np.empty((len(px.x), 6), dtype=np.float32)
    _fill_rays(px.x, px.y, *camera_axes(w2c), rays)
    return rays


def camera_axes(w2c: FloatArray) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """(3, 3) camera -> world rotation and (3,) camera centre, float32 as the rays have them."""
    eye = -w2c[:3, :3].T @ w2c[:3, 3]
    return w2c[:3, :3].T.astype(np.float32), eye.astype(np.float32)


_jit = numba.njit(nogil=True, cache=True)


@_jit
def _fill_rays(x: Any, y: Any, rot_cw: Any, eye: Any, rays: Any) -> None:
    """rays[p] = eye, ``_direction(p)``; rays (n, 6) C-contiguous, written through a flat view
    with the row offset in a variable (5x faster than 2-d indexing or an inline offset)."""
    flat = rays.reshape(-1)
    for p in range(len(x)):
        _put_ray(flat, p, x, y, rot_cw, eye, p)


@_jit
def _put_ray(flat: Any, m: int, x: Any, y: Any, rot_cw: Any, eye: Any, p: int) -> None:
    """Ray m of the flat (n * 6) rays: the eye and pixel p's ``_direction``."""
    row = 6 * m
    for i in range(3):
        flat[row + i] = eye[i]
        flat[row + 3 + i] = _direction(x[p], y[p], rot_cw, i)


@_jit
def fill_rays_in_box(x: Any, y: Any, rot_cw: Any, eye: Any, box: Any, rays: Any,
                      cast: Any) -> int:
    """``_fill_rays`` for the rays that may meet ``box`` (2, 3), packed at the front of
    ``rays`` in pixel order; cast[p] says whether pixel p's ray is there (``CAST``, else
    ``NOT_CAST``). Returns their count.

    Slab test in float64 on the float32 direction open3d is given: a ray is left out only when
    its entry into the box (at t >= 0) comes after its exit.
    """
    flat = rays.reshape(-1)
    m = 0
    for p in range(len(x)):
        enter, leave = 0.0, np.inf
        for i in range(3):
            d = np.float64(_direction(x[p], y[p], rot_cw, i))
            o = np.float64(eye[i])
            if d == 0.0:
                if o < box[0, i] or o > box[1, i]:
                    enter = np.inf
            else:
                t0, t1 = (box[0, i] - o) / d, (box[1, i] - o) / d
                enter, leave = max(enter, min(t0, t1)), min(leave, max(t0, t1))
        cast[p] = CAST if enter <= leave else NOT_CAST
        if enter <= leave:
            _put_ray(flat, m, x, y, rot_cw, eye, p)
            m += 1
    return m


# Margin of the image-plane outline of a box, in pixels: far above the float32
# rounding of the directions open3d is given (~1e-7 of a normalised coordinate).
OUTLINE_MARGIN_PX = 2.0


# One pass over the pixel rows with the box's slab tests unrolled: a compiled loop's branches.
@_jit
def box_outline(x: Any, y: Any, rot_cw: Any, eye: Any, box: Any, margin: Any,  # noqa: C901
                lo: Any, hi: Any) -> bool:
    """Per pixel row, the column range [lo, hi] (normalised x) whose rays may meet ``box``.

    The box's corners are projected into the image; a ray meets the box only where its pixel
    lies in their convex hull. The hull's x range over the band of the row's y +- margin[1] is
    taken from the corners inside the band and from where each segment between two corners
    crosses its edges, then widened by margin[0]. Returns False (nothing written) where a
    corner is not in front of the camera, so that the hull is not the outline, or the box is
    unbounded.

    Args:
        x: (w,) the columns' normalised x; y: (h,) the rows' normalised y.
        margin: (2,) normalised x and y margins.
    """
    if not np.all(np.isfinite(box)):
        return False
    cx, cy = np.empty(8), np.empty(8)
    for k in range(8):
        rel = (np.float64(box[k & 1, 0]) - eye[0], np.float64(box[(k >> 1) & 1, 1]) - eye[1],
               np.float64(box[(k >> 2) & 1, 2]) - eye[2])
        cam = [0.0, 0.0, 0.0]
        for j in range(3):
            for i in range(3):
                cam[j] += np.float64(rot_cw[i, j]) * rel[i]
        if cam[2] <= 1e-9:
            return False
        cx[k], cy[k] = cam[0] / cam[2], cam[1] / cam[2]
    for r in range(len(y)):
        band = (np.float64(y[r]) - margin[1], np.float64(y[r]) + margin[1])
        left, right = np.inf, -np.inf
        for a in range(8):
            if band[0] <= cy[a] <= band[1]:
                left, right = min(left, cx[a]), max(right, cx[a])
            for b in range(a + 1, 8):
                if cy[a] == cy[b]:
                    continue
                for edge in band:
                    if (cy[a] - edge) * (cy[b] - edge) <= 0:
                        at = cx[a] + (edge - cy[a]) * (cx[b] - cx[a]) / (cy[b] - cy[a])
                        left, right = min(left, at), max(right, at)
        lo[r], hi[r] = left - margin[0], right + margin[0]
    return True


# The compiled kernels take flat arrays, as numba's nopython mode does not take records.
@_jit
def fill_rays_in_outline(x: Any, y: Any, rot_cw: Any, eye: Any, width: int,  # noqa: PLR0913
                         lo: Any, hi: Any, table: Any, rays: Any, cast: Any,
                         table_t: Any) -> int:
    """``fill_rays_in_box`` for the rays within the rows' ranges of ``box_outline``; of the
    others, with a support plane ``table`` (see ``StagedScene.table_m``; None: nothing
    outside the outline), those that meet it are ``ON_TABLE`` at depth ``table_t[p]``, those
    near its border are cast too (``_meet_table``)."""
    flat = rays.reshape(-1)
    columns = x[:width].astype(np.float64)  # increasing
    m = 0
    for r in range(len(lo)):
        start = r * width
        first = start + np.searchsorted(columns, lo[r], side="left")
        last = start + np.searchsorted(columns, hi[r], side="right")
        if table is not None:
            _meet_table(columns, np.float64(y[start]), rot_cw, eye, table,
                        cast[start:start + width], table_t[start:start + width])
        else:
            cast[start:start + width] = NOT_CAST
        for p in range(first, last):
            cast[p] = CAST
        for p in range(start, start + width):
            if cast[p] == CAST:
                _put_ray(flat, m, x, y, rot_cw, eye, p)
                m += 1
    return m


@_jit
def _meet_table(x: Any, y: Any, rot_cw: Any, eye: Any, table: Any, cast: Any, table_t: Any
                ) -> None:
    """Where the rays of one pixel row (normalised x of its columns, y) meet the plane
    z = table[0], in float64: ``ON_TABLE`` (table_t = its depth) more than table[5] inside
    the square, ``NOT_CAST`` more than that outside it or when the ray leaves the plane
    behind, else ``CAST`` (near the border, where open3d's float32 test may decide either
    way, or with the eye at the plane's height)."""
    pad = table[5]
    height = table[0] - np.float64(eye[2])
    # the direction R (x, y, 1) of each column is a + x b
    a = np.empty(3)
    b = np.empty(3)
    for i in range(3):
        a[i] = np.float64(rot_cw[i, 1]) * y + np.float64(rot_cw[i, 2])
        b[i] = np.float64(rot_cw[i, 0])
    if abs(height) <= pad:  # the eye at the plane's height
        cast[:] = CAST
        return
    for c in range(len(x)):
        rise = a[2] + x[c] * b[2]
        if rise == 0.0:
            cast[c] = CAST
            continue
        t = height / rise
        hx = np.float64(eye[0]) + t * (a[0] + x[c] * b[0])
        hy = np.float64(eye[1]) + t * (a[1] + x[c] * b[1])
        if t <= 0.0 or hx < table[1] - pad or hx > table[2] + pad or hy < table[3] - pad \
                or hy > table[4] + pad:
            cast[c] = NOT_CAST
        elif table[1] + pad < hx < table[2] - pad and table[3] + pad < hy < table[4] - pad:
            cast[c] = ON_TABLE
            table_t[c] = np.float32(t)
        else:
            cast[c] = CAST


@_jit
def _direction(x: Any, y: Any, rot_cw: Any, i: int) -> Any:
    """Component i of the world direction rot_cw @ (x, y, 1), float32, summed left to right."""
    return x * rot_cw[i, 0] + y * rot_cw[i, 1] + rot_cw[i, 2]


KEY_LIGHT = np.array([0.3, -0.4, 1.0], dtype=np.float32) / np.float32(math.sqrt(1.25))


@_jit
def shade_pixels(hit: Any, px: Any, rot_cw: Any, tables: Any, light: Any, out: Any) -> None:
    """Per pixel: z-depth (0 on a miss), |cos| of the view angle, instance id and colour.

    hit: open3d's (t_hit, geometry ids as int32, primitive normals) of the rays cast, packed in
    pixel order, cast (``CAST``, ``ON_TABLE`` or ``NOT_CAST`` per pixel), the depths on the
    table and its geometry id; px: the grid's (x, y, inv_norm); tables:
    (instance_of, shade_table, background); light: float32 (key x, y, z, headlight weight, key
    weight, offset), weights and offset in light levels; out: (depth, cos, instance, colour),
    (h, w) images.
    """
    t, gid, normal, cast, table_t, table_id = hit
    x, y, inv_norm = px
    instance_of, shade_table, background = tables
    depth, cos, instance = out[0].reshape(-1), out[1].reshape(-1), out[2].reshape(-1)
    colour = out[3].reshape((len(x), 3))
    top = np.float32(LEVELS - 0.5)
    up = np.zeros(3, dtype=np.float32)
    up[2] = 1  # the table's normal, as open3d gives it for its two triangles
    j = -1
    for p in range(len(x)):
        g, tp, n = MISS, np.float32(0), up
        if cast[p] == CAST:
            j += 1
            g, tp, n = gid[j], t[j], normal[j]
        elif cast[p] == ON_TABLE:
            g, tp = table_id, table_t[p]
        if g == MISS:
            depth[p], cos[p], instance[p] = 0, 0, 0
            for i in range(3):
                colour[p, i] = background[i]
            continue
        ndotv, key = np.float32(0), np.float32(0)
        for i in range(3):
            ndotv += n[i] * _direction(x[p], y[p], rot_cw, i)
            key += n[i] * light[i]
        ndotv *= inv_norm[p]
        key = max(-key if ndotv > 0 else key, np.float32(0))  # normal flipped to the camera
        depth[p], cos[p], instance[p] = tp, abs(ndotv), instance_of[g]
        row = g * LEVELS + int(min(light[5] + light[3] * abs(ndotv) + light[4] * key, top))
        for i in range(3):
            colour[p, i] = shade_table[row, i]


def light(ambient: float) -> npt.NDArray[np.float32]:
    """``shade_pixels``'s light: a headlight (0.6) and a key light from above (0.4), two-sided
    normals, ``ambient`` floor, in light levels (0.5 added: the int cast truncates)."""
    scale = (1 - ambient) * (LEVELS - 1)
    return np.array([*KEY_LIGHT, 0.6 * scale, 0.4 * scale, ambient * (LEVELS - 1) + 0.5],
                    dtype=np.float32)


@_jit
def shade_and_measure(hit: Any, px: Any, rot_cw: Any, tables: Any,  # noqa: PLR0913
                      light: Any, out: Any, model: Any, rng: Any, measured: Any,
                      field: Any) -> None:
    """``shade_pixels``, then the sensor model on its depth into ``measured`` (h, w): one call
    without the GIL, so all of a frame's pixel work overlaps the next view's ray cast."""
    shade_pixels(hit, px, rot_cw, tables, light, out)
    measure_depth(out[0], out[1], model, rng, measured, field)
