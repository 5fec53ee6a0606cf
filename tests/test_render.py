"""Tests of cadio.camera.render and .noise: camera geometry, view path, instance ids, noise."""

from __future__ import annotations

import inspect
import math

import numpy as np
import open3d as o3d
import pytest
from scipy import stats
from scipy.ndimage import binary_dilation

from cadio.camera.noise import NoiseConfig, apply_noise
from cadio.camera.raycast import camera_rays, pixel_grid
from cadio.camera.render import (
    CaptureConfig,
    PlacedPart,
    camera_intrinsics,
    camera_pose,
    render_view,
    render_views,
    scene_bounds_mm,
    scene_meta,
    scene_scale,
)
from cadio.records import Mesh

CLEAN = CaptureConfig(support_plane=False, elevation_deg=0.0, target_size_m=None)


def box_mesh(sx: float, sy: float, sz: float) -> Mesh:
    """An axis-aligned box centred on the origin, mm."""
    m = o3d.geometry.TriangleMesh.create_box(sx, sy, sz)
    m.translate((-sx / 2, -sy / 2, -sz / 2))
    return Mesh(np.asarray(m.vertices, dtype=np.float64), np.asarray(m.triangles, dtype=np.int64))


def cylinder_mesh(radius: float, height: float) -> Mesh:
    """A closed cylinder about +Z centred on the origin, mm."""
    m = o3d.geometry.TriangleMesh.create_cylinder(radius, height, resolution=48)
    return Mesh(np.asarray(m.vertices, dtype=np.float64), np.asarray(m.triangles, dtype=np.int64))


def pose(tx: float, ty: float, tz: float, rz_deg: float = 0.0) -> np.ndarray:
    c, s = math.cos(math.radians(rz_deg)), math.sin(math.radians(rz_deg))
    p = np.eye(4)
    p[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    p[:3, 3] = [tx, ty, tz]
    return p


def cube_scene() -> list[PlacedPart]:
    """A 100 mm cube centred at (200, 300, 50) mm."""
    return [PlacedPart(1, box_mesh(100, 100, 100), pose(200, 300, 50), "#c03030")]


def pair_scene() -> list[PlacedPart]:
    """A box and a cylinder standing on z = 0, 60 mm apart, both turned about Z."""
    return [PlacedPart(1, box_mesh(100, 80, 60), pose(-90, 0, 30, 20), "#c03030", "box"),
            PlacedPart(2, cylinder_mesh(30, 120), pose(90, 10, 60, 0), "#3050c0", "cyl")]


def test_intrinsics_have_the_papers_field_of_view() -> None:
    k = camera_intrinsics(CaptureConfig())
    assert (k.width, k.height) == (640, 480)
    assert math.degrees(2 * math.atan((k.width / 2) / k.fx)) == pytest.approx(49.2, abs=1e-9)
    assert k.fx == k.fy and (k.cx, k.cy) == (319.5, 239.5)


def test_125_views_are_2_88_degrees_apart_at_1_6_m() -> None:
    cfg = CaptureConfig()
    centre = np.array([0.1, -0.2, 0.05])
    eyes = []
    for v in range(cfg.n_views):
        w2c = camera_pose(cfg, v, centre)
        eye = -w2c[:3, :3].T @ w2c[:3, 3]
        assert np.linalg.norm(eye - centre) == pytest.approx(1.6, abs=1e-12)
        seen = w2c[:3, :3] @ centre + w2c[:3, 3]  # the centre is on the optical axis
        assert seen[:2] == pytest.approx([0, 0], abs=1e-12) and seen[2] > 0
        eyes.append(eye - centre)
    az = np.degrees(np.unwrap([math.atan2(e[1], e[0]) for e in eyes]))
    assert np.diff(az) == pytest.approx(np.full(124, 2.88), abs=1e-9)
    assert cfg.n_views * cfg.step_deg == pytest.approx(360.0)
    elevation = math.degrees(math.asin(eyes[0][2] / 1.6))
    assert elevation == pytest.approx(cfg.elevation_deg)


def test_view_zero_looks_along_plus_y_with_z_up() -> None:
    w2c = camera_pose(CaptureConfig(elevation_deg=0.0), 0, np.zeros(3))
    assert w2c[2, :3] == pytest.approx([0, 1, 0])  # camera z (forward) is world +Y
    assert w2c[1, :3] == pytest.approx([0, 0, -1])  # camera y (down) is world -Z
    assert w2c[0, :3] == pytest.approx([1, 0, 0])  # camera x (right) is world +X


def test_cube_projects_where_expected_with_z_depth() -> None:
    frame = render_view(cube_scene(), CLEAN, 0)
    k = frame.intrinsics
    face = frame.instance == 1
    # Camera 1.6 m from the cube centre on -Y; the front face is 50 mm nearer, fronto-parallel,
    # so every pixel on it has z-depth 1.55 m (a range image would grow towards the corners).
    assert frame.depth[face] == pytest.approx(np.full(face.sum(), 1.55), abs=1e-5)
    v, u = np.nonzero(face)
    half = k.fx * 0.05 / 1.55
    assert u.min() == pytest.approx(k.cx - half, abs=1.0)
    assert u.max() == pytest.approx(k.cx + half, abs=1.0)
    assert v.min() == pytest.approx(k.cy - half, abs=1.0)
    assert v.max() == pytest.approx(k.cy + half, abs=1.0)
    assert np.all(frame.depth[~face] == 0) and np.all(frame.instance[~face] == 0)


def test_rays_are_the_float32_pinhole_directions() -> None:
    # Depth is t_hit of these very rays: their bits are part of the output.
    cfg = CaptureConfig(width=64, height=48)
    px = pixel_grid(camera_intrinsics(cfg))
    w2c = camera_pose(cfg, 7, np.array([0.1, -0.2, 0.05]))
    rot = w2c[:3, :3].T.astype(np.float32)
    eye = (-w2c[:3, :3].T @ w2c[:3, 3]).astype(np.float32)
    rays = camera_rays(w2c, px)
    for i in range(3):
        assert np.all(rays[:, i] == eye[i])
        assert np.array_equal(rays[:, 3 + i], px.x * rot[i, 0] + px.y * rot[i, 1] + rot[i, 2])


def test_views_render_lazily_and_stamp_their_meta() -> None:
    cfg = CaptureConfig(n_views=4, start_deg=10.0, step_deg=90.0, width=64, height=48)
    gen = render_views(cube_scene(), cfg)
    assert inspect.isgenerator(gen)
    frames = list(gen)
    assert [f.meta["view_index"] for f in frames] == [0, 1, 2, 3]
    assert [f.meta["azimuth_deg"] for f in frames] == [10.0, 100.0, 190.0, 280.0]
    assert [f.timestamp_ns for f in frames] == [0, 10**8, 2 * 10**8, 3 * 10**8]
    (only,) = render_views(cube_scene(), cfg, views=[2])
    assert np.array_equal(only.depth, frames[2].depth)


def test_views_cast_ahead_are_the_views_rendered_alone() -> None:
    cfg = CaptureConfig(n_views=3, width=64, height=48, noise=NoiseConfig())
    for frame in render_views(pair_scene(), cfg):
        alone = render_view(pair_scene(), cfg, frame.meta["view_index"])
        for name in ("depth", "colour", "instance", "world_to_camera"):
            assert np.array_equal(getattr(frame, name), getattr(alone, name))
    gen = render_views(pair_scene(), cfg)
    next(gen)
    gen.close()  # with the next view in flight: waits for it, raises nothing


def test_scene_is_scaled_to_the_target_size() -> None:
    parts = pair_scene()
    cfg = CaptureConfig(target_size_m=0.3)
    lo, hi = scene_bounds_mm(parts)
    scale = scene_scale(parts, cfg)
    assert scale * float(np.max(hi - lo)) == pytest.approx(0.3)
    frame = render_view(parts, cfg, 5)
    assert frame.meta["scale_m_per_mm"] == pytest.approx(scale)
    meta = scene_meta(parts, cfg, {"left": [[1, 2]]})
    assert meta["scale_m_per_mm"] == pytest.approx(scale)
    assert [p["instance_id"] for p in meta["parts"]] == [1, 2]
    assert np.array(meta["parts"][0]["pose_mm"]) == pytest.approx(parts[0].pose)


def test_instance_ids_match_the_parts() -> None:
    parts = pair_scene()
    frame = render_view(parts, CaptureConfig(), 7)
    assert set(np.unique(frame.instance)) == {0, 1, 2}
    # The box is red and the cylinder blue: the colour under each id must say so.
    red = frame.colour[frame.instance == 1].astype(int)
    blue = frame.colour[frame.instance == 2].astype(int)
    assert np.all(red[:, 0] > red[:, 2]) and np.all(blue[:, 2] > blue[:, 0])
    assert np.all(frame.depth[frame.instance > 0] > 0)


def test_noise_off_is_exact_and_noise_is_seeded() -> None:
    parts = pair_scene()
    clean = render_view(parts, CaptureConfig(), 3)
    again = render_view(parts, CaptureConfig(), 3)
    assert np.array_equal(clean.depth, again.depth)
    assert np.array_equal(clean.colour, again.colour)
    a = render_view(parts, CaptureConfig(noise=NoiseConfig(seed=1)), 3)
    b = render_view(parts, CaptureConfig(noise=NoiseConfig(seed=1)), 3)
    c = render_view(parts, CaptureConfig(noise=NoiseConfig(seed=2)), 3)
    assert np.array_equal(a.depth, b.depth) and not np.array_equal(a.depth, c.depth)
    assert np.array_equal(a.instance, clean.instance) and np.array_equal(a.colour, clean.colour)


def test_noise_has_the_configured_depth_statistics() -> None:
    noise = NoiseConfig(sigma_base_m=0.001, sigma_quadratic_per_m=0.002, quantisation_m=0.0)
    frame = render_view(cube_scene(), CaptureConfig(
        support_plane=False, elevation_deg=0.0, target_size_m=None, noise=noise), 0)
    inner = (render_view(cube_scene(), CLEAN, 0).instance == 1) & (frame.depth > 0)
    residual = frame.depth[inner].astype(np.float64) - 1.55
    expected = 0.001 + 0.002 * 1.55**2
    assert inner.sum() > 1500
    assert np.std(residual) == pytest.approx(expected, rel=0.1)
    assert abs(np.mean(residual)) < 3 * expected / math.sqrt(inner.sum())

    stepped = render_view(cube_scene(), CaptureConfig(
        support_plane=False, elevation_deg=0.0, target_size_m=None, noise=NoiseConfig()), 0)
    mm = stepped.depth[stepped.depth > 0].astype(np.float64) * 1000
    assert mm == pytest.approx(np.round(mm), abs=1e-3)  # 1 mm quantisation


def test_noise_drops_grazing_angles_and_depth_edges() -> None:
    # A large table seen from 20 degrees: its far part is grazing (incidence up to ~80 deg).
    cfg = CaptureConfig(elevation_deg=20.0, support_size_m=4.0)
    parts = pair_scene()
    clean = render_view(parts, cfg, 0)
    noisy = render_view(parts, CaptureConfig(elevation_deg=20.0, support_size_m=4.0,
                                             noise=NoiseConfig()), 0)
    # Incidence on the support plane (normal +Z) from each pixel's ray direction.
    k = clean.intrinsics
    v, u = np.mgrid[0 : k.height, 0 : k.width]
    rays_cam = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones(u.shape)], axis=-1)
    rays = rays_cam @ clean.world_to_camera[:3, :3]  # camera -> world directions
    cos_inc = np.abs(rays[..., 2]) / np.linalg.norm(rays, axis=-1)
    plane = (clean.instance == 0) & (clean.depth > 0)
    grazing = plane & (cos_inc < math.cos(math.radians(75.0)))
    facing = plane & (cos_inc > math.cos(math.radians(70.0)))
    assert grazing.sum() > 1000 and facing.sum() > 1000
    assert np.all(noisy.depth[grazing] == 0)
    assert np.mean(noisy.depth[facing] > 0) > 0.97
    # Silhouettes of the parts against the plane are depth discontinuities: dropped.
    jump = np.zeros(clean.depth.shape, dtype=bool)
    jump[:, 1:] |= np.abs(np.diff(clean.depth, axis=1)) > 0.05
    assert jump.sum() > 50 and np.all(noisy.depth[jump] == 0)


def two_walls(near_m: float = 0.8, far_m: float = 2.5) -> np.ndarray:
    """(400, 600) depth: a wall at ``near_m`` on the left half and one at ``far_m`` on the right,
    both seen head-on (cos incidence 1); one depth discontinuity, between columns 299 and 300."""
    depth = np.full((400, 600), near_m, dtype=np.float32)
    depth[:, 300:] = far_m
    return depth


def test_noise_is_unbiased_and_normal_with_sigma_growing_as_depth_squared() -> None:
    noise = NoiseConfig(sigma_base_m=0.0005, sigma_quadratic_per_m=0.0012, quantisation_m=0.0)
    depth = two_walls()
    noisy = apply_noise(depth, np.ones_like(depth), noise, view=4)
    for z, side in ((0.8, np.s_[:, :299]), (2.5, np.s_[:, 301:])):
        residual = noisy[side].astype(np.float64) - z
        sigma = noise.sigma_base_m + noise.sigma_quadratic_per_m * z**2
        assert residual.size > 100_000
        assert np.std(residual) == pytest.approx(sigma, rel=0.02)
        assert abs(np.mean(residual)) < 4 * sigma / math.sqrt(residual.size)
        assert stats.kstest(residual.ravel() / sigma, "norm").pvalue > 1e-3


def test_noise_draws_are_independent_per_pixel_and_per_view() -> None:
    noise = NoiseConfig(quantisation_m=0.0)
    depth = np.full((300, 400), 1.6, dtype=np.float32)
    cos = np.ones_like(depth)
    first, second = (apply_noise(depth, cos, noise, view) for view in (0, 1))
    assert np.array_equal(apply_noise(depth, cos, noise, 0), first)
    a, b = (noisy.astype(np.float64) - 1.6 for noisy in (first, second))
    bound = 5 / math.sqrt(depth.size)  # |correlation| of independent draws: ~1 / sqrt(n)
    for x, y in ((a, b), (a[:, 1:], a[:, :-1]), (a[1:], a[:-1])):
        assert abs(np.corrcoef(x.ravel(), y.ravel())[0, 1]) < bound


def test_random_dropout_and_wider_edges_drop_their_share() -> None:
    depth = two_walls()
    noisy = apply_noise(depth, np.ones_like(depth), NoiseConfig(dropout=0.1), view=0)
    assert np.mean(noisy[:, :299] == 0) == pytest.approx(0.1, abs=0.005)
    wide = apply_noise(depth, np.ones_like(depth), NoiseConfig(edge_width_px=3), view=0)
    assert np.flatnonzero(np.all(wide == 0, axis=0)).tolist() == list(range(297, 303))
    assert np.all(wide[:, :297] > 0) and np.all(wide[:, 303:] > 0)


def reference_edges(depth: np.ndarray, jump_m: float, width_px: int) -> np.ndarray:
    """Depth edges in plain numpy: pixels beside a jump over ``jump_m`` (a miss is far away),
    dilated by the 4-neighbour cross ``width_px - 1`` times."""
    z = np.where(depth > 0, depth, np.float32(1e6))
    edge = np.zeros(depth.shape, dtype=bool)
    rows, cols = np.abs(np.diff(z, axis=0)) > jump_m, np.abs(np.diff(z, axis=1)) > jump_m
    edge[1:] |= rows
    edge[:-1] |= rows
    edge[:, 1:] |= cols
    edge[:, :-1] |= cols
    return binary_dilation(edge, iterations=width_px - 1) if width_px > 1 else edge


@pytest.mark.parametrize("width_px", [1, 2, 4])
def test_depth_edges_match_a_numpy_reference(width_px: int) -> None:
    rng = np.random.default_rng(width_px)
    blocks = rng.choice([0.0, 0.9, 0.91, 1.5], size=(12, 16)).astype(np.float32)
    depth = np.kron(blocks, np.ones((7, 9), dtype=np.float32))  # 84 x 144, steps and holes
    noisy = apply_noise(depth, np.ones_like(depth), NoiseConfig(edge_width_px=width_px), view=0)
    expected_missing = reference_edges(depth, 0.02, width_px) | (depth == 0)
    assert np.array_equal(noisy == 0, expected_missing)


@pytest.mark.parametrize("cfg", [
    CaptureConfig(n_views=4, step_deg=90.0),  # a table under the pair: its edges cut the box
    CaptureConfig(n_views=3, step_deg=120.0, support_plane=False, elevation_deg=-30.0,
                  noise=NoiseConfig(seed=5)),
    # from under the table (it is two-sided), noise on
    CaptureConfig(n_views=3, step_deg=120.0, elevation_deg=-20.0, noise=NoiseConfig(seed=3)),
])
def test_rays_left_out_beside_the_scene_box_change_no_pixel(cfg: CaptureConfig) -> None:
    """Only rays that may meet a part are cast (and those near the support plane's border);
    casting every ray gives the same frames, bit for bit, noise included, except that the
    table's depth comes from a closed form within float32 rounding of open3d's."""
    from dataclasses import replace

    from cadio.camera.raycast import CAST, ON_TABLE
    from cadio.camera.render import _cast, _frame, stage_scene

    parts = pair_scene()
    staged = stage_scene(parts, cfg)
    unbounded = np.array([[-np.inf] * 3, [np.inf] * 3])
    every = replace(staged, box_m=unbounded, parts_box_m=unbounded, table_m=None)
    px = pixel_grid(camera_intrinsics(cfg))
    rays = np.empty((len(px.x), 6), dtype=np.float32)
    for view in range(cfg.n_views):
        culled = _cast(staged, cfg, px, view, rays)
        cast, on_table = culled.hit[3] == CAST, culled.hit[3] == ON_TABLE
        assert 0 < np.count_nonzero(cast) < len(cast)  # some left out, some cast
        assert np.any(on_table) == cfg.support_plane
        a = _frame(staged, cfg, px, culled)
        full = _cast(every, cfg, px, view, rays)
        assert np.all(full.hit[3] == CAST)
        b = _frame(every, cfg, px, full)
        for image in ("colour", "instance"):
            assert np.array_equal(getattr(a, image), getattr(b, image))
        table = on_table.reshape(a.depth.shape)
        assert np.array_equal(a.depth[~table], b.depth[~table])
        # a reading may round to the next millimetre where the two depths straddle a step
        step = cfg.noise.quantisation_m if cfg.noise else 0.0
        np.testing.assert_allclose(a.depth[table], b.depth[table], rtol=1e-6, atol=1.01 * step)
        if cfg.noise:
            assert np.count_nonzero(a.depth[table] != b.depth[table]) <= \
                1e-3 * np.count_nonzero(table)
        assert np.all(b.instance[table] == 0)
        # every ray left out misses the scene
        assert not np.any(b.depth.reshape(-1)[~(cast | on_table.reshape(-1))] > 0)


def test_the_box_outline_casts_every_ray_the_slab_test_casts() -> None:
    """The outline of the box's projected corners (per pixel row, plus a margin) holds every
    pixel whose ray the exact slab test sends; a camera inside the box has no outline."""
    from cadio.camera.raycast import (
        box_outline,
        camera_axes,
        fill_rays_in_box,
        fill_rays_in_outline,
    )
    from cadio.camera.render import stage_scene

    cfg = CaptureConfig(n_views=12, step_deg=30.0, elevation_deg=50.0)
    staged = stage_scene(pair_scene(), cfg)
    k = camera_intrinsics(cfg)
    px = pixel_grid(k)
    rays = np.empty((len(px.x), 6), dtype=np.float32)
    exact, outline = (np.empty(len(px.x), dtype=np.int8) for _ in range(2))
    table_t = np.empty(len(px.x), dtype=np.float32)
    lo, hi = np.empty(k.height), np.empty(k.height)
    margin = np.array([2.0 / k.fx, 2.0 / k.fy])
    for view in range(cfg.n_views):
        rot_cw, eye = camera_axes(camera_pose(cfg, view, staged.centre_m))
        fill_rays_in_box(px.x, px.y, rot_cw, eye, staged.box_m, rays, exact)
        assert box_outline(px.x[:k.width], px.y[::k.width], rot_cw, eye.astype(np.float64),
                            staged.box_m, margin, lo, hi)
        m = fill_rays_in_outline(px.x, px.y, rot_cw, eye, k.width, lo, hi, None, rays, outline,
                                  table_t)
        assert m == np.count_nonzero(outline)
        assert np.all(outline[exact == 1])  # never a ray left out that the slab test casts
        assert np.count_nonzero(outline) <= 1.05 * np.count_nonzero(exact)  # and few more
        w = np.flatnonzero(outline)
        directions = rays[:m, 3:]
        assert np.array_equal(directions[:, 0], (px.x[w] * rot_cw[0, 0] + px.y[w] * rot_cw[0, 1]
                                                 + rot_cw[0, 2]).astype(np.float32))
    inside = staged.box_m.mean(axis=0)
    assert not box_outline(px.x[:k.width], px.y[::k.width], rot_cw, inside, staged.box_m,
                            margin, lo, hi)


def test_the_d435_model_has_the_datasheet_rms_at_inspection_range_in_millimetre_steps() -> None:
    from cadio.camera.noise import D435

    for z, rms_mm in ((0.5, 0.95), (0.6, 1.37), (1.0, 3.8)):
        depth = np.full((240, 320), z, dtype=np.float32)
        noisy = apply_noise(depth, np.ones_like(depth), D435, view=0)
        seen = noisy[noisy > 0].astype(np.float64)
        assert np.std(seen - z) * 1000 == pytest.approx(rms_mm, rel=0.1)
        assert np.allclose(seen * 1000, np.round(seen * 1000), atol=1e-3)  # 1 mm steps
        assert 0.005 < 1 - seen.size / depth.size < 0.02  # its 1% dropout


def test_correlated_noise_errs_together_so_averaging_does_not_wash_it_out() -> None:
    depth = np.full((480, 640), 0.6, dtype=np.float32)
    cos = np.ones_like(depth)
    white = NoiseConfig(sigma_base_m=0.0, sigma_quadratic_per_m=0.0038, quantisation_m=0.0)
    smooth = NoiseConfig(sigma_base_m=0.0, sigma_quadratic_per_m=0.0038, quantisation_m=0.0,
                         correlated_fraction=0.5, correlated_px=8)
    sigma = 0.0038 * 0.36
    for cfg, patch_sd in ((white, sigma / 32), (smooth, sigma * math.sqrt(0.5) / 2)):
        noisy = apply_noise(depth, cos, cfg, view=3).astype(np.float64) - 0.6
        assert np.std(noisy) == pytest.approx(sigma, rel=0.05)  # the same per-pixel rms
        means = noisy.reshape(15, 32, 20, 32).mean(axis=(1, 3))  # 32 x 32 px patches
        assert np.std(means) == pytest.approx(patch_sd, rel=0.6)
    # without the correlated share, the per-pixel draws are those of the model before it
    again = apply_noise(depth, cos, NoiseConfig(quantisation_m=0.0), view=3)
    assert np.array_equal(again, apply_noise(depth, cos, NoiseConfig(quantisation_m=0.0,
                                                                      correlated_px=4), view=3))
