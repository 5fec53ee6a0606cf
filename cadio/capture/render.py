"""Simulated RGB-D captures of CAD scenes: colour, depth and instance ids by ray casting.

Follows the paper's protocol (views 2.88 degrees apart about the vertical Z axis, 125 of them,
horizontal field of view 49.2 degrees, camera 1.6 m from the scene, 640x480), rendered with
open3d's ``RaycastingScene`` rather than Blender: one ray per pixel, built from the intrinsic
matrix and the camera pose in the OpenCV convention (x right, y down, z forward). Each ray's
direction has a camera-frame z component of exactly 1, so the hit distance ``t_hit`` *is* the
z-depth (verified in tests against an analytic box).

Frames: the world frame is the scene frame scaled to metres (``scale_m_per_mm``, chosen so the
scene's largest extent is ``target_size_m``), so a part's points in its own millimetre
coordinates are ``inverse(pose) @ (p_world / scale)``. Colour is Lambertian shading (a
headlight plus a key light from above) of each part's sRGB colour. An optional sensor model
(``cadio.capture.noise``) adds depth-dependent noise, quantisation and the holes a real structured
light / time-of-flight camera leaves at grazing angles and at depth discontinuities.

Speed: the per-pixel work (rays, shading, the sensor model) runs in compiled loops (numba) that
release the GIL. open3d's ``cast_rays`` holds it, so ``render_views`` works on a frame's pixels
on a worker thread while the next view is cast; ``bench/capture.py`` measures the whole against
bare ``cast_rays`` of the same rays. Only the rays whose pixels lie in the image outline of the
parts' box are cast; the others meet the support plane, intersected in closed form (colour,
instance and cos exactly as cast, depth within float32 rounding), or nothing. Near the plane's
border, where the two could disagree, rays are cast.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Any, TypeVar, cast

import numba
import numpy as np
import numpy.typing as npt
import open3d as o3d

from cadio.capture.noise import NoiseConfig, measure_depth, sensor_model, sensor_rng
from cadio.records import CameraIntrinsics, FloatArray, Mesh, RgbdFrame, apply_pose

Colour = str | tuple[float, float, float]
_MISS = -1  # open3d's geometry id for a ray that hits nothing, 0xFFFFFFFF, read as int32
# What became of a pixel's ray: nothing in its way (a miss), cast by open3d, or meeting the
# support plane in closed form.
_NOT_CAST, _CAST, _ON_TABLE = 0, 1, 2
# Shading goes through a table of (geometry, light level) -> sRGB: per-pixel float colour
# arithmetic and np.power cost more than the ray cast itself.
_LEVELS = 1024
# The scene's box is padded by this (relative to its largest coordinate, metres) before rays
# are tested against it: far above the float32 rounding of open3d's ray-triangle tests.
_BOX_PAD = 1e-5


@dataclass(frozen=True)
class PlacedPart:
    """One part placed in a scene.

    instance_id: >= 1 (0 means background and the support plane).
    mesh: the part in its own coordinates, millimetres.
    pose: (4, 4) float64, part -> scene, millimetres.
    colour: sRGB, either "#rrggbb" or (r, g, b) in [0, 1].
    """

    instance_id: int
    mesh: Mesh
    pose: FloatArray
    colour: Colour = "#b4b4b4"
    part_id: str = ""
    label: str = ""


@dataclass(frozen=True)
class CaptureConfig:
    """Camera path, sensor and scene staging. Angles in degrees, lengths in metres."""

    n_views: int = 125
    step_deg: float = 2.88  # paper: 125 views 2.88 degrees apart cover 360 degrees
    start_deg: float = 0.0  # azimuth 0: camera on -Y looking along +Y (DESIGN's observer)
    elevation_deg: float = 25.0  # slightly above the scene, as a camera over a workbench
    distance_m: float = 1.6  # paper: camera 1.6 m from the object (here: the scene centre)
    hfov_deg: float = 49.2
    width: int = 640
    height: int = 480
    target_size_m: float | None = 0.3  # largest scene extent after scaling; None: real size
    support_plane: bool = True  # a table under the scene (instance 0), needed to test RANSAC
    support_size_m: float = 1.2
    support_colour: Colour = "#8c8c8c"
    background: tuple[int, int, int] = (24, 24, 24)  # sRGB where rays hit nothing
    ambient: float = 0.25  # fraction of the albedo lit regardless of orientation
    frame_period_ns: int = 100_000_000  # view k is stamped k * period
    noise: NoiseConfig | None = None

    def __post_init__(self) -> None:
        if not (abs(self.elevation_deg) < 90 and 0 < self.hfov_deg < 180):
            raise ValueError("need |elevation_deg| < 90 and 0 < hfov_deg < 180")
        if min(self.n_views, self.width, self.height) < 1 or self.distance_m <= 0:
            raise ValueError("n_views, width, height and distance_m must be positive")


@dataclass(frozen=True)
class StagedScene:
    """A scene ready to ray-cast: the open3d scene (world metres) and per-geometry lookups."""

    scene: Any  # o3d.t.geometry.RaycastingScene
    instance_of: npt.NDArray[np.int32]  # by open3d geometry id
    shade_table: npt.NDArray[np.uint8]  # (g * _LEVELS, 3) sRGB of each albedo at each light
    scale_m_per_mm: float
    centre_m: FloatArray
    meta: dict[str, Any] = field(default_factory=dict)
    # (2, 3) float64 world box of every triangle, padded (``_BOX_PAD``): a ray that misses it
    # hits nothing and is not cast
    box_m: npt.NDArray[np.float64] = field(
        default_factory=lambda: np.array([[-np.inf] * 3, [np.inf] * 3]))
    # The same of the parts alone: a ray outside its outline meets no part.
    parts_box_m: npt.NDArray[np.float64] = field(
        default_factory=lambda: np.array([[-np.inf] * 3, [np.inf] * 3]))
    # The support plane, if any, as open3d holds it: (z, x0, x1, y0, y1, pad) world metres
    # (pad: ``_BOX_PAD``'s margin; within it of its border rays are cast), and its geometry id.
    table_m: npt.NDArray[np.float64] | None = None
    table_id: int = -1


def camera_intrinsics(cfg: CaptureConfig) -> CameraIntrinsics:
    """Square-pixel pinhole with the horizontal field of view ``cfg.hfov_deg``.

    The principal point is the image centre in OpenCV's convention (pixel centres at integer
    coordinates), so (cx, cy) = ((w - 1) / 2, (h - 1) / 2).
    """
    f = (cfg.width / 2.0) / math.tan(math.radians(cfg.hfov_deg) / 2.0)
    return CameraIntrinsics(cfg.width, cfg.height, f, f, (cfg.width - 1) / 2, (cfg.height - 1) / 2)


def view_azimuth_deg(cfg: CaptureConfig, view: int) -> float:
    """Azimuth of view ``view`` about +Z, degrees (counter-clockwise seen from above)."""
    return cfg.start_deg + view * cfg.step_deg


def camera_pose(cfg: CaptureConfig, view: int, centre_m: FloatArray) -> FloatArray:
    """world_to_camera (4, 4), metres, OpenCV axes, for view ``view`` looking at ``centre_m``.

    The camera sits ``distance_m`` from the centre at ``elevation_deg`` above the horizontal,
    rotated by the view's azimuth about +Z from the -Y side; image "up" is world +Z.
    """
    az, el = math.radians(view_azimuth_deg(cfg, view)), math.radians(cfg.elevation_deg)
    offset = cfg.distance_m * np.array(
        [math.cos(el) * math.sin(az), -math.cos(el) * math.cos(az), math.sin(el)]
    )
    eye = np.asarray(centre_m, dtype=np.float64) + offset
    forward = -offset / np.linalg.norm(offset)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot_cw = np.column_stack([right, down, forward])  # camera axes in world
    w2c = np.eye(4)
    w2c[:3, :3] = rot_cw.T
    w2c[:3, 3] = -rot_cw.T @ eye
    return w2c


def srgb_to_linear(colour: Colour) -> npt.NDArray[np.float32]:
    """(3,) linear RGB in [0, 1] from "#rrggbb" or an sRGB triple in [0, 1]."""
    if isinstance(colour, str):
        h = colour.lstrip("#")
        c = np.array([int(h[i : i + 2], 16) / 255.0 for i in (0, 2, 4)])
    else:
        c = np.asarray(colour, dtype=np.float64)
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return lin.astype(np.float32)


def _linear_to_srgb8(lin: npt.NDArray[np.float32]) -> npt.NDArray[np.uint8]:
    c = np.clip(lin, 0.0, 1.0)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


def scene_bounds_mm(parts: Iterable[PlacedPart]) -> tuple[FloatArray, FloatArray]:
    """Axis-aligned bounds (min, max) of the posed parts in the scene frame, mm."""
    pts = np.vstack([apply_pose(p.pose, p.mesh.vertices) for p in parts])
    return pts.min(axis=0), pts.max(axis=0)


def scene_scale(parts: list[PlacedPart], cfg: CaptureConfig) -> float:
    """Metres per scene millimetre: ``target_size_m`` over the largest extent (or 1e-3)."""
    if cfg.target_size_m is None:
        return 1e-3
    lo, hi = scene_bounds_mm(parts)
    extent = float(np.max(hi - lo))
    if extent <= 0:
        raise ValueError("scene has zero extent")
    return cfg.target_size_m / extent


def _support_plane(lo_m: FloatArray, hi_m: FloatArray, size_m: float) -> Any:
    """A square (two triangles, normal +Z) under the scene at its lowest z."""
    cx, cy, z = (lo_m[0] + hi_m[0]) / 2, (lo_m[1] + hi_m[1]) / 2, lo_m[2]
    s = size_m / 2
    v = np.array([[cx - s, cy - s, z], [cx + s, cy - s, z], [cx + s, cy + s, z],
                  [cx - s, cy + s, z]], dtype=np.float32)
    return v, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)


def _add(scene: Any, vertices: npt.NDArray[Any], triangles: npt.NDArray[Any]) -> int:
    return int(scene.add_triangles(
        o3d.core.Tensor.from_numpy(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor.from_numpy(np.ascontiguousarray(triangles, dtype=np.uint32)),
    ))


def stage_scene(parts: list[PlacedPart], cfg: CaptureConfig) -> StagedScene:
    """Scale and pose every part into the world frame (metres) and build the ray caster."""
    if not parts:
        raise ValueError("a scene needs at least one part")
    if len({p.instance_id for p in parts}) != len(parts) or min(p.instance_id for p in parts) < 1:
        raise ValueError("instance ids must be unique and >= 1")
    scale = scene_scale(parts, cfg)
    lo, hi = scene_bounds_mm(parts)
    scene = o3d.t.geometry.RaycastingScene()
    instance, albedo = [], []
    box = np.array([[np.inf] * 3, [-np.inf] * 3])

    def add(vertices: npt.NDArray[Any], triangles: npt.NDArray[Any]) -> int:
        placed = np.asarray(vertices, dtype=np.float32)  # what open3d holds
        box[0], box[1] = np.minimum(box[0], placed.min(axis=0)), np.maximum(box[1],
                                                                            placed.max(axis=0))
        return _add(scene, placed, triangles)

    for p in parts:
        add(scale * apply_pose(p.pose, p.mesh.vertices), p.mesh.triangles)
        instance.append(p.instance_id)
        albedo.append(srgb_to_linear(p.colour))
    parts_box = box.copy()
    table_m, table_id = None, -1
    if cfg.support_plane:
        corners, triangles = _support_plane(scale * lo, scale * hi, cfg.support_size_m)
        table_id = add(corners, triangles)
        instance.append(0)
        albedo.append(srgb_to_linear(cfg.support_colour))
        c = corners.astype(np.float64)
        table_m = np.array([c[0, 2], c[:, 0].min(), c[:, 0].max(), c[:, 1].min(), c[:, 1].max(),
                            0.0])
    pad = _BOX_PAD * (1.0 + float(np.max(np.abs(box))))
    box += np.array([[-pad], [pad]])
    parts_box += np.array([[-pad], [pad]])
    if table_m is not None:
        table_m[5] = pad
    centre = scale * (lo + hi) / 2
    levels = np.linspace(0, 1, _LEVELS, dtype=np.float32)
    table = _linear_to_srgb8(np.asarray(albedo)[:, None, :] * levels[None, :, None])
    return StagedScene(scene, np.asarray(instance, dtype=np.int32), table.reshape(-1, 3),
                       scale, centre, {"scale_m_per_mm": scale,
                                       "scene_centre_m": centre.tolist()}, box, parts_box,
                       table_m, table_id)


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
    _fill_rays(px.x, px.y, *_camera_axes(w2c), rays)
    return rays


def _camera_axes(w2c: FloatArray) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """(3, 3) camera -> world rotation and (3,) camera centre, float32 as the rays have them."""
    eye = -w2c[:3, :3].T @ w2c[:3, 3]
    return w2c[:3, :3].T.astype(np.float32), eye.astype(np.float32)


# Compiled, GIL-free loops: as numpy passes over 307k pixels this work cost about as much as
# cast_rays itself, and could not run while cast_rays (which holds the GIL) cast the next view.
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
def _fill_rays_in_box(x: Any, y: Any, rot_cw: Any, eye: Any, box: Any, rays: Any,
                      cast: Any) -> int:
    """``_fill_rays`` for the rays that may meet ``box`` (2, 3), packed at the front of
    ``rays`` in pixel order; cast[p] says whether pixel p's ray is there (``_CAST``, else
    ``_NOT_CAST``). Returns their count.

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
        cast[p] = _CAST if enter <= leave else _NOT_CAST
        if enter <= leave:
            _put_ray(flat, m, x, y, rot_cw, eye, p)
            m += 1
    return m


# Margin of the image-plane outline of a box, in pixels: far above the float32
# rounding of the directions open3d is given (~1e-7 of a normalised coordinate).
_OUTLINE_MARGIN_PX = 2.0


@_jit
def _box_outline(x: Any, y: Any, rot_cw: Any, eye: Any, box: Any, margin: Any, lo: Any,
                 hi: Any) -> bool:
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


@_jit
def _fill_rays_in_outline(x: Any, y: Any, rot_cw: Any, eye: Any, width: int, lo: Any, hi: Any,
                          table: Any, rays: Any, cast: Any, table_t: Any) -> int:
    """``_fill_rays_in_box`` for the rays within the rows' ranges of ``_box_outline``; of the
    others, with a support plane ``table`` (see ``StagedScene.table_m``; None: nothing
    outside the outline), those that meet it are ``_ON_TABLE`` at depth ``table_t[p]``, those
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
            cast[start:start + width] = _NOT_CAST
        for p in range(first, last):
            cast[p] = _CAST
        for p in range(start, start + width):
            if cast[p] == _CAST:
                _put_ray(flat, m, x, y, rot_cw, eye, p)
                m += 1
    return m


@_jit
def _meet_table(x: Any, y: Any, rot_cw: Any, eye: Any, table: Any, cast: Any, table_t: Any
                ) -> None:
    """Where the rays of one pixel row (normalised x of its columns, y) meet the plane
    z = table[0], in float64: ``_ON_TABLE`` (table_t = its depth) more than table[5] inside
    the square, ``_NOT_CAST`` more than that outside it or when the ray leaves the plane
    behind, else ``_CAST`` (near the border, where open3d's float32 test may decide either
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
        cast[:] = _CAST
        return
    for c in range(len(x)):
        rise = a[2] + x[c] * b[2]
        if rise == 0.0:
            cast[c] = _CAST
            continue
        t = height / rise
        hx = np.float64(eye[0]) + t * (a[0] + x[c] * b[0])
        hy = np.float64(eye[1]) + t * (a[1] + x[c] * b[1])
        if t <= 0.0 or hx < table[1] - pad or hx > table[2] + pad or hy < table[3] - pad \
                or hy > table[4] + pad:
            cast[c] = _NOT_CAST
        elif table[1] + pad < hx < table[2] - pad and table[3] + pad < hy < table[4] - pad:
            cast[c] = _ON_TABLE
            table_t[c] = np.float32(t)
        else:
            cast[c] = _CAST


@_jit
def _direction(x: Any, y: Any, rot_cw: Any, i: int) -> Any:
    """Component i of the world direction rot_cw @ (x, y, 1), float32, summed left to right."""
    return x * rot_cw[i, 0] + y * rot_cw[i, 1] + rot_cw[i, 2]


_KEY_LIGHT = np.array([0.3, -0.4, 1.0], dtype=np.float32) / np.float32(math.sqrt(1.25))


@_jit
def _shade_pixels(hit: Any, px: Any, rot_cw: Any, tables: Any, light: Any, out: Any) -> None:
    """Per pixel: z-depth (0 on a miss), |cos| of the view angle, instance id and colour.

    hit: open3d's (t_hit, geometry ids as int32, primitive normals) of the rays cast, packed in
    pixel order, cast (``_CAST``, ``_ON_TABLE`` or ``_NOT_CAST`` per pixel), the depths on the
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
    top = np.float32(_LEVELS - 0.5)
    up = np.zeros(3, dtype=np.float32)
    up[2] = 1  # the table's normal, as open3d gives it for its two triangles
    j = -1
    for p in range(len(x)):
        g, tp, n = _MISS, np.float32(0), up
        if cast[p] == _CAST:
            j += 1
            g, tp, n = gid[j], t[j], normal[j]
        elif cast[p] == _ON_TABLE:
            g, tp = table_id, table_t[p]
        if g == _MISS:
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
        row = g * _LEVELS + int(min(light[5] + light[3] * abs(ndotv) + light[4] * key, top))
        for i in range(3):
            colour[p, i] = shade_table[row, i]


def _light(ambient: float) -> npt.NDArray[np.float32]:
    """``_shade_pixels``'s light: a headlight (0.6) and a key light from above (0.4), two-sided
    normals, ``ambient`` floor, in light levels (0.5 added: the int cast truncates)."""
    scale = (1 - ambient) * (_LEVELS - 1)
    return np.array([*_KEY_LIGHT, 0.6 * scale, 0.4 * scale, ambient * (_LEVELS - 1) + 0.5],
                    dtype=np.float32)


@dataclass(frozen=True)
class _Cast:
    """One view and what open3d's ``cast_rays`` returned for it (numpy views)."""

    view: int
    w2c: FloatArray
    # t_hit, geometry ids as int32, primitive normals (of the rays cast), what became of each
    # pixel's ray (_CAST, _ON_TABLE, _NOT_CAST), the depths on the table, its geometry id
    hit: tuple[Any, ...]


def _cast(staged: StagedScene, cfg: CaptureConfig, px: PixelGrid, view: int,
          rays: npt.NDArray[np.float32]) -> _Cast:
    """Cast a view's rays that may meet a part (or the support plane near its border), built
    in ``rays`` (reused from view to view: a fresh 7 MB array each time costs page faults);
    the support plane's others are intersected in closed form, the rest hit nothing. open3d
    spends about as long on a ray that meets the two-triangle plane as on one that meets a part.
    """
    w2c = camera_pose(cfg, view, staged.centre_m)
    cast = np.empty(len(px.x), dtype=np.int8)
    table_t = np.empty(len(px.x), dtype=np.float32)
    rot_cw, eye = _camera_axes(w2c)
    k = camera_intrinsics(cfg)
    lo, hi = np.empty(k.height), np.empty(k.height)
    margin = np.array([_OUTLINE_MARGIN_PX / k.fx, _OUTLINE_MARGIN_PX / k.fy])
    outline = px.x[:k.width], px.y[::k.width], rot_cw, eye.astype(np.float64)
    if _box_outline(*outline, staged.parts_box_m, margin, lo, hi):
        m = _fill_rays_in_outline(px.x, px.y, rot_cw, eye, k.width, lo, hi, staged.table_m,
                                  rays, cast, table_t)
    else:  # a corner of the parts' box is not in front of the camera: each ray is tested
        m = _fill_rays_in_box(px.x, px.y, rot_cw, eye, staged.box_m, rays, cast)
    ans = staged.scene.cast_rays(o3d.core.Tensor.from_numpy(rays[:m]))
    return _Cast(view, w2c, (ans["t_hit"].numpy(), ans["geometry_ids"].numpy().view(np.int32),
                             ans["primitive_normals"].numpy(), cast, table_t, staged.table_id))


@_jit
def _shade_and_measure(hit: Any, px: Any, rot_cw: Any, tables: Any, light: Any, out: Any,
                       model: Any, rng: Any, measured: Any) -> None:
    """``_shade_pixels``, then the sensor model on its depth into ``measured`` (h, w): one call
    without the GIL, so all of a frame's pixel work overlaps the next view's ray cast."""
    _shade_pixels(hit, px, rot_cw, tables, light, out)
    measure_depth(out[0], out[1], model, rng, measured)


def _frame(staged: StagedScene, cfg: CaptureConfig, px: PixelGrid, c: _Cast) -> RgbdFrame:
    """The frame of a cast view (runs on the worker thread)."""
    k = camera_intrinsics(cfg)
    shape = (k.height, k.width)
    out = (np.empty(shape, np.float32), np.empty(shape, np.float32), np.empty(shape, np.int32),
           np.empty((*shape, 3), np.uint8))
    tables = (staged.instance_of, staged.shade_table, np.asarray(cfg.background, np.uint8))
    pixels = (c.hit, (px.x, px.y, px.inv_norm), _camera_axes(c.w2c)[0], tables,
              _light(cfg.ambient), out)
    depth = out[0]
    if cfg.noise is None:
        _shade_pixels(*pixels)
    else:
        depth = np.empty(shape, np.float32)
        _shade_and_measure(*pixels, sensor_model(cfg.noise), sensor_rng(cfg.noise, c.view), depth)
    meta = {**staged.meta, "view_index": c.view, "azimuth_deg": view_azimuth_deg(cfg, c.view),
            "elevation_deg": cfg.elevation_deg, "noise": cfg.noise is not None}
    return RgbdFrame(timestamp_ns=c.view * cfg.frame_period_ns, intrinsics=k, colour=out[3],
                     depth=depth, world_to_camera=c.w2c, instance=out[2], meta=meta)


_In = TypeVar("_In")
_Out = TypeVar("_Out")


def _overlapped(items: Iterator[_In], work: Callable[[_In], _Out]) -> Iterator[_Out]:
    """``work(item)`` for each item, on a worker thread while the next item is produced here.

    The generator is one item ahead of its consumer; closing it waits for the worker.
    """
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="render") as pool:
        pending: Future[_Out] | None = None
        for item in items:
            submitted = pool.submit(work, item)
            if pending is not None:
                yield pending.result()
            pending = submitted
        if pending is not None:
            yield pending.result()


def render_views(parts: list[PlacedPart], cfg: CaptureConfig | None = None,
                 views: Iterable[int] | None = None) -> Iterator[RgbdFrame]:
    """Render views of a scene lazily, one ``RgbdFrame`` at a time.

    A frame's pixels are worked on (on a thread) while the next view is cast, so the
    generator runs one ray cast ahead of its consumer.

    Args:
        parts: the scene (one part, a pair or an assembly), meshes in mm, poses in mm.
        cfg: camera path and sensor; defaults to the paper's protocol without noise.
        views: view indices to render (default ``range(cfg.n_views)``).
    Yields:
        RgbdFrame: colour (h, w, 3) uint8 sRGB; depth (h, w) float32 metres, 0 where missing;
        instance (h, w) int32 (0 = background/support; the true visible surface, also where
        the noise model drops the depth); world_to_camera (4, 4) metres with
        world = scene frame scaled by ``meta["scale_m_per_mm"]``.
    """
    cfg = cfg or CaptureConfig()
    staged = stage_scene(parts, cfg)
    px = pixel_grid(camera_intrinsics(cfg))
    rays = np.empty((len(px.x), 6), dtype=np.float32)
    order = range(cfg.n_views) if views is None else views
    casts = (_cast(staged, cfg, px, view, rays) for view in order)
    yield from _overlapped(casts, lambda c: _frame(staged, cfg, px, c))


def render_view(parts: list[PlacedPart], cfg: CaptureConfig | None = None,
                view: int = 0) -> RgbdFrame:
    """One view of a scene (see ``render_views``)."""
    return next(render_views(parts, cfg, [view]))


def scene_meta(parts: list[PlacedPart], cfg: CaptureConfig | None = None,
               labels: dict[str, Any] | None = None) -> dict[str, Any]:
    """JSON-ready description of a scene for the capture's ``/scene`` channel.

    Keys: ``scale_m_per_mm``, ``scene_centre_m``, ``parts`` (instance_id, part_id, label,
    colour, ``pose_mm`` as a nested 4x4 list, part -> scene), ``config`` and ``labels``
    (ground truth supplied by the caller, e.g. relations between part ids).
    """
    cfg = cfg or CaptureConfig()
    scale = scene_scale(parts, cfg)
    lo, hi = scene_bounds_mm(parts)
    meta = {
        "format": "mateqa.scene/1",
        "scale_m_per_mm": scale,
        "scene_centre_m": (scale * (lo + hi) / 2).tolist(),
        "parts": [
            {"instance_id": p.instance_id, "part_id": p.part_id, "label": p.label,
             "colour": p.colour if isinstance(p.colour, str) else list(p.colour),
             "pose_mm": np.asarray(p.pose, dtype=np.float64).tolist()}
            for p in parts
        ],
        "config": asdict(cfg),
        "labels": labels or {},
    }
    return cast(dict[str, Any], json.loads(json.dumps(meta)))  # plain JSON types: round trips
