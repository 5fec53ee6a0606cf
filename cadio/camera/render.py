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
(``cadio.camera.noise``) adds depth-dependent noise, quantisation and the holes a real structured
light / time-of-flight camera leaves at grazing angles and at depth discontinuities.

Speed: the per-pixel work (rays, shading, the sensor model) runs in compiled loops (numba,
``cadio.camera.raycast``) that release the GIL. open3d's ``cast_rays`` holds it, so
``render_views`` works on a frame's pixels on a worker thread while the next view is cast;
``bench/speed/capture.py`` measures the whole against bare ``cast_rays`` of the same rays. Only the
rays whose pixels lie in the image outline of the parts' box are cast; the others meet the
support plane, intersected in closed form (colour, instance and cos exactly as cast, depth
within float32 rounding), or nothing. Near the plane's border, where the two could disagree,
rays are cast.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Any, TypeVar, cast

import numpy as np
import numpy.typing as npt
import open3d as o3d

from cadio.camera import CIRCLE_VIEWS
from cadio.camera.noise import NoiseConfig, sensor_field, sensor_model, sensor_rng
from cadio.camera.raycast import (
    LEVELS,
    OUTLINE_MARGIN_PX,
    PixelGrid,
    box_outline,
    camera_axes,
    fill_rays_in_box,
    fill_rays_in_outline,
    light,
    pixel_grid,
    shade_and_measure,
    shade_pixels,
)
from cadio.records import CameraIntrinsics, FloatArray, Mesh, RgbdFrame, apply_pose

Colour = str | tuple[float, float, float]
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

    n_views: int = CIRCLE_VIEWS
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
    shade_table: npt.NDArray[np.uint8]  # (g * LEVELS, 3) sRGB of each albedo at each light
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
    levels = np.linspace(0, 1, LEVELS, dtype=np.float32)
    table = _linear_to_srgb8(np.asarray(albedo)[:, None, :] * levels[None, :, None])
    return StagedScene(scene, np.asarray(instance, dtype=np.int32), table.reshape(-1, 3),
                       scale, centre, {"scale_m_per_mm": scale,
                                       "scene_centre_m": centre.tolist()}, box, parts_box,
                       table_m, table_id)


@dataclass(frozen=True)
class _Cast:
    """One view and what open3d's ``cast_rays`` returned for it (numpy views)."""

    view: int
    w2c: FloatArray
    # t_hit, geometry ids as int32, primitive normals (of the rays cast), what became of each
    # pixel's ray (CAST, ON_TABLE, NOT_CAST), the depths on the table, its geometry id
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
    rot_cw, eye = camera_axes(w2c)
    k = camera_intrinsics(cfg)
    lo, hi = np.empty(k.height), np.empty(k.height)
    margin = np.array([OUTLINE_MARGIN_PX / k.fx, OUTLINE_MARGIN_PX / k.fy])
    outline = px.x[:k.width], px.y[::k.width], rot_cw, eye.astype(np.float64)
    if box_outline(*outline, staged.parts_box_m, margin, lo, hi):
        m = fill_rays_in_outline(px.x, px.y, rot_cw, eye, k.width, lo, hi, staged.table_m,
                                  rays, cast, table_t)
    else:  # a corner of the parts' box is not in front of the camera: each ray is tested
        m = fill_rays_in_box(px.x, px.y, rot_cw, eye, staged.box_m, rays, cast)
    ans = staged.scene.cast_rays(o3d.core.Tensor.from_numpy(rays[:m]))
    return _Cast(view, w2c, (ans["t_hit"].numpy(), ans["geometry_ids"].numpy().view(np.int32),
                             ans["primitive_normals"].numpy(), cast, table_t, staged.table_id))


def _frame(staged: StagedScene, cfg: CaptureConfig, px: PixelGrid, c: _Cast) -> RgbdFrame:
    """The frame of a cast view (runs on the worker thread)."""
    k = camera_intrinsics(cfg)
    shape = (k.height, k.width)
    out = (np.empty(shape, np.float32), np.empty(shape, np.float32), np.empty(shape, np.int32),
           np.empty((*shape, 3), np.uint8))
    tables = (staged.instance_of, staged.shade_table, np.asarray(cfg.background, np.uint8))
    pixels = (c.hit, (px.x, px.y, px.inv_norm), camera_axes(c.w2c)[0], tables,
              light(cfg.ambient), out)
    depth = out[0]
    if cfg.noise is None:
        shade_pixels(*pixels)
    else:
        depth = np.empty(shape, np.float32)
        shade_and_measure(*pixels, sensor_model(cfg.noise), sensor_rng(cfg.noise, c.view), depth,
                          sensor_field(cfg.noise, c.view, shape))
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
