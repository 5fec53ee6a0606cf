"""Tests of cadio.capture.pointcloud and .segment: back-projection, segmentation, sampling."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest

from cadio.camera.noise import NoiseConfig
from cadio.camera.render import CaptureConfig, PlacedPart, render_view, scene_meta
from cadio.capture.pointcloud import (
    backproject,
    part_clouds,
    sample_points,
    to_part_frame,
    valid_depth,
)
from cadio.capture.segment import adjusted_rand_index, segment_clusters, segmentation_score
from cadio.records import Mesh, RgbdFrame

CFG = CaptureConfig(elevation_deg=25.0, target_size_m=0.3)
NOISY = CaptureConfig(elevation_deg=25.0, target_size_m=0.3, noise=NoiseConfig(seed=3))


def _mesh(m: o3d.geometry.TriangleMesh) -> Mesh:
    return Mesh(np.asarray(m.vertices, dtype=np.float64), np.asarray(m.triangles, dtype=np.int64))


def _pose(t: tuple[float, float, float], rz_deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(rz_deg)), math.sin(math.radians(rz_deg))
    p = np.eye(4)
    p[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    p[:3, 3] = t
    return p


def pair() -> list[PlacedPart]:
    """A box and a cylinder on the table, 60 mm apart, turned about Z; meshes off-centre."""
    box = o3d.geometry.TriangleMesh.create_box(100, 80, 60)  # corner at the origin
    cyl = o3d.geometry.TriangleMesh.create_cylinder(30, 120, resolution=48)
    return [PlacedPart(1, _mesh(box), _pose((-140, -40, 0), 25), "#c03030", "box"),
            PlacedPart(2, _mesh(cyl), _pose((90, 10, 60), 0), "#3050c0", "cyl")]


@pytest.fixture(scope="module")
def clean() -> RgbdFrame:
    return render_view(pair(), CFG, 11)


@pytest.fixture(scope="module")
def noisy() -> RgbdFrame:
    return render_view(pair(), NOISY, 11)


def _distance_to_mesh(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def test_backprojected_points_lie_on_their_part_within_a_mm(clean: RgbdFrame) -> None:
    meta = scene_meta(pair(), CFG)
    clouds = part_clouds(clean, meta)
    for part in pair():
        pts = clouds[part.instance_id]
        assert len(pts) > 1000
        # Part millimetres; float32 rays at 1.6 m are good to ~0.1 micrometre of scene.
        assert np.max(_distance_to_mesh(part.mesh, pts)) < 0.05


def test_to_part_frame_undoes_scale_and_pose() -> None:
    part = pair()[0]
    scale = 0.0025
    world = scale * (part.mesh.vertices @ part.pose[:3, :3].T + part.pose[:3, 3])
    assert to_part_frame(world, part.pose, scale) == pytest.approx(part.mesh.vertices, abs=1e-9)


def test_backproject_returns_world_metres(clean: RgbdFrame) -> None:
    pts = backproject(clean)
    assert len(pts) == np.count_nonzero(valid_depth(clean))
    table = backproject(clean, clean.instance == 0)
    # The table lies at the scene's lowest z, which is 0: both parts stand on z = 0 mm.
    assert table[:, 2] == pytest.approx(np.zeros(len(table)), abs=1e-6)
    assert np.all(np.abs(pts[:, :2]) < 1.0)  # metres, not millimetres: within the 1.2 m table


@pytest.mark.parametrize("which", ["clean", "noisy"])
def test_segmentation_without_ids_matches_the_ids(which: str, request: pytest.FixtureRequest
                                                  ) -> None:
    frame: RgbdFrame = request.getfixturevalue(which)
    labels = segment_clusters(frame)
    assert frame.instance is not None
    score = segmentation_score(labels, frame.instance, valid_depth(frame))
    assert set(score.iou) == {1, 2}
    # Points within the plane band (5 mm) at the parts' feet are lost with the table.
    assert score.mean_iou > 0.9 and min(score.iou.values()) > 0.88
    assert score.ari > 0.85


def test_segmentation_score_of_the_truth_is_perfect(clean: RgbdFrame) -> None:
    assert clean.instance is not None
    score = segmentation_score(clean.instance * 7, clean.instance)
    assert score.mean_iou == 1.0 and score.ari == pytest.approx(1.0)


def test_adjusted_rand_index_invariants() -> None:
    rng = np.random.default_rng(0)
    a = rng.integers(0, 4, 500)
    assert adjusted_rand_index(a, a) == pytest.approx(1.0)
    assert adjusted_rand_index(a, (a + 1) % 4) == pytest.approx(1.0)  # relabelled
    assert abs(adjusted_rand_index(a, rng.integers(0, 4, 500))) < 0.05  # chance level


def test_sample_points_gives_600_spread_points(clean: RgbdFrame) -> None:
    pts = part_clouds(clean, scene_meta(pair(), CFG))[2]
    fps = sample_points(pts, 600, seed=1)
    rnd = sample_points(pts, 600, seed=1, method="random")
    assert fps.shape == rnd.shape == (600, 3)
    assert np.array_equal(fps, sample_points(pts, 600, seed=1))
    as_set = {tuple(p) for p in pts}
    assert all(tuple(p) in as_set for p in fps)
    assert len({tuple(p) for p in fps}) == 600

    def nearest(s: np.ndarray) -> float:
        d = np.linalg.norm(s[:, None] - s[None], axis=-1) + np.eye(len(s)) * 1e9
        return float(np.min(d, axis=1).mean())

    assert nearest(fps) > nearest(rnd)  # farthest-point sampling covers the part evenly
    few = sample_points(pts[:10], 600)
    assert few.shape == (600, 3) and np.array_equal(few[:10], pts[:10])
    with pytest.raises(ValueError):
        sample_points(pts[:0])


def test_farthest_point_sampling_picks_what_the_plain_loop_picks() -> None:
    """The compiled sampler against the numpy loop it replaced, ties included."""
    def reference(pts: np.ndarray, k: int) -> np.ndarray:
        rng = np.random.default_rng(0)
        chosen = [int(rng.integers(len(pts)))]
        dist = np.sum((pts - pts[chosen[0]]) ** 2, axis=1)
        for _ in range(1, k):
            chosen.append(int(np.argmax(dist)))
            dist = np.minimum(dist, np.sum((pts - pts[chosen[-1]]) ** 2, axis=1))
        return pts[chosen]

    rng = np.random.default_rng(3)
    for pts in (rng.normal(size=(2000, 3)), np.round(rng.normal(size=(900, 3)), 1)):
        assert np.array_equal(sample_points(pts, 600), reference(pts, 600))


def test_a_stride_keeps_every_stride_th_point(clean: RgbdFrame) -> None:
    assert clean.instance is not None
    table = clean.instance == 0
    assert np.array_equal(backproject(clean, table, stride=8), backproject(clean, table)[::8])
