"""Tests of reports.metrics: invariants first (IoU(a, a) = 1, metrics unchanged when both grids
move together), then small cases worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest

from reports.metrics import (
    METRICS,
    MetricsConfig,
    bbox_diagonal,
    chamfer_l1,
    composition_error,
    downsample,
    fscore,
    iou,
    missing,
    part_metrics,
    projection_overlap,
    surface_points,
)

Grid = npt.NDArray[np.bool_]


def _box(lo: tuple[int, int, int], hi: tuple[int, int, int], n: int = 16) -> Grid:
    grid = np.zeros((n, n, n), dtype=bool)
    grid[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = True
    return grid


def _ball(n: int, radius: float = 0.37) -> Grid:
    """A ball sampled at the voxel centres of an n^3 unit cube, off the grid's centre."""
    x = (np.arange(n) + 0.5) / n
    xx, yy, zz = np.meshgrid(x, x, x, indexing="ij")
    return np.asarray((xx - 0.5) ** 2 + (yy - 0.47) ** 2 + (zz - 0.52) ** 2 <= radius**2)


def _pair() -> tuple[Grid, Grid]:
    """An L-shaped truth with no symmetry, and a prediction that is off by a few voxels."""
    truth = _box((10, 10, 8), (40, 20, 30), n=64) | _box((10, 10, 8), (20, 45, 16), n=64)
    pred = np.roll(truth, (2, -1, 1), axis=(0, 1, 2))
    pred[30:44, 12:18, 20:34] = True
    pred[12:16, 30:40, 8:12] = False
    return pred, truth


def _random_grids(seed: int) -> tuple[Grid, Grid]:
    rng = np.random.default_rng(seed)
    return rng.random((12, 12, 12)) < 0.3, rng.random((12, 12, 12)) < 0.5


@pytest.mark.parametrize("seed", range(5))
def test_iou_is_one_on_itself_symmetric_and_bounded(seed: int) -> None:
    a, b = _random_grids(seed)
    assert iou(a, a) == 1.0
    assert iou(a, b) == iou(b, a)
    assert 0.0 < iou(a, b) < 1.0


def test_iou_of_empty_grids() -> None:
    empty, full = np.zeros((4, 4, 4), dtype=bool), np.ones((4, 4, 4), dtype=bool)
    assert iou(empty, empty) == 1.0
    assert iou(empty, full) == 0.0


def test_iou_of_two_boxes_by_hand() -> None:
    # 64 voxels each, sharing a 2x4x4 slab of 32: 32 / (64 + 64 - 32) = 1/3.
    assert iou(_box((2, 2, 2), (6, 6, 6)), _box((4, 2, 2), (8, 6, 6))) == pytest.approx(1 / 3)


def test_iou_refuses_other_shapes_and_probabilities() -> None:
    with pytest.raises(ValueError, match="shape"):
        iou(np.zeros((4, 4, 4), dtype=bool), np.zeros((4, 4, 5), dtype=bool))
    with pytest.raises(ValueError, match="bool"):
        iou(np.full((4, 4, 4), 0.7), np.zeros((4, 4, 4), dtype=bool))


def test_projection_overlap_of_a_shifted_box_by_hand() -> None:
    box = _box((2, 2, 2), (6, 6, 6))
    moved = _box((4, 2, 3), (8, 6, 7))  # 2 voxels along x, 1 along z
    # xy (along z): 4x4 squares shifted by 2 in x: 8 / 24. yz (along x): shifted by 1 in z:
    # 12 / 20. zx (along y): shifted by 2 in x and 1 in z: 6 / 26.
    assert projection_overlap(moved, box, "xy") == pytest.approx(8 / 24)
    assert projection_overlap(moved, box, "yz") == pytest.approx(12 / 20)
    assert projection_overlap(moved, box, "zx") == pytest.approx(6 / 26)
    with pytest.raises(ValueError, match="unknown plane"):
        projection_overlap(moved, box, "xz")


def test_quarter_turn_about_z_keeps_xy_and_swaps_yz_with_zx() -> None:
    pred, truth = _pair()
    before = part_metrics(pred, truth, voxel_mm=0.5)
    turned = part_metrics(np.rot90(pred, axes=(0, 1)), np.rot90(truth, axes=(0, 1)), 0.5)
    assert turned["overlap_yz"] == pytest.approx(before["overlap_zx"])
    assert turned["overlap_zx"] == pytest.approx(before["overlap_yz"])
    assert before["overlap_yz"] != pytest.approx(before["overlap_zx"])  # the swap is visible
    for name in set(METRICS) - {"overlap_yz", "overlap_zx"}:
        assert turned[name] == pytest.approx(before[name]), name


def test_metrics_unchanged_when_both_grids_move_within_the_grid() -> None:
    pred, truth = _pair()
    # Even shifts keep the 2x2x2 blocks pooled into 32^3 cells whole: iou32 pools other
    # voxels after an odd one, as it would pool another grid placement.
    shift = {"shift": (4, -6, 16), "axis": (0, 1, 2)}
    moved = part_metrics(np.roll(pred, **shift), np.roll(truth, **shift), voxel_mm=0.5)
    assert moved == pytest.approx(part_metrics(pred, truth, voxel_mm=0.5))


def test_composition_error_and_missing_by_hand() -> None:
    truth = _box((2, 2, 2), (6, 6, 6))  # 64 voxels
    pred = _box((2, 2, 3), (6, 6, 6)) | _box((8, 8, 8), (10, 10, 10))  # 48 right, 8 wrong
    assert composition_error(pred, truth) == pytest.approx(8 / 56)
    assert missing(pred, truth) == pytest.approx(16 / 64)
    ce, m = composition_error(pred, truth), missing(pred, truth)
    assert 1 / iou(pred, truth) == pytest.approx(1 / (1 - ce) + 1 / (1 - m) - 1)


def test_an_empty_prediction_has_no_composition_error_and_misses_everything() -> None:
    truth = _box((2, 2, 2), (6, 6, 6))
    empty = np.zeros_like(truth)
    assert math.isnan(composition_error(empty, truth))
    assert missing(empty, truth) == 1.0
    assert composition_error(truth, truth) == 0.0 and missing(truth, truth) == 0.0


def _points(*rows: tuple[float, float, float]) -> npt.NDArray[np.float64]:
    return np.array(rows, dtype=np.float64).reshape(-1, 3)


def test_chamfer_of_identical_sets_symmetric_and_by_hand() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(80, 3))
    assert chamfer_l1(a, a) == 0.0
    assert chamfer_l1(a, b) == pytest.approx(chamfer_l1(b, a))
    # Far-apart points moved by (3, 4, 0): every nearest neighbour is 5 mm away.
    lattice = 100.0 * _points((0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 1))
    assert chamfer_l1(lattice + np.array([3.0, 4.0, 0.0]), lattice) == pytest.approx(5.0)
    # Directed means 0 (pred -> truth) and (0 + 10) / 2 (truth -> pred): (0 + 5) / 2.
    assert chamfer_l1(_points((0, 0, 0)), _points((0, 0, 0), (10, 0, 0))) == pytest.approx(2.5)


def test_chamfer_with_an_empty_set() -> None:
    one = _points((1, 2, 3))
    assert math.isnan(chamfer_l1(_points(), one))
    assert chamfer_l1(_points(), _points()) == 0.0


def test_fscore_by_hand() -> None:
    truth = _points((0, 0, 0), (10, 0, 0))
    assert fscore(truth, truth, threshold_mm=0.0) == 1.0
    assert fscore(truth + np.array([0.0, 0.0, 5.0]), truth, threshold_mm=5.0) == 1.0  # at = within
    assert fscore(truth + np.array([0.0, 0.0, 5.0]), truth, threshold_mm=4.9) == 0.0
    # precision 1/2 (one of two predicted points is near), recall 1: F = 2/3.
    assert fscore(truth, _points((0, 0, 0)), threshold_mm=1.0) == pytest.approx(2 / 3)
    assert fscore(_points(), truth, threshold_mm=1.0) == 0.0
    with pytest.raises(ValueError, match="non-negative"):
        fscore(truth, truth, threshold_mm=-1.0)


def test_downsample_by_majority_with_ties_inside() -> None:
    grid = np.zeros((4, 4, 4), dtype=bool)
    grid[:2, :2, :2].flat[:4] = True  # 4 of 8: a tie, occupied
    grid[2:, 2:, 2:].flat[:3] = True  # 3 of 8: empty
    coarse = downsample(grid, 2)
    assert coarse.shape == (2, 2, 2)
    assert coarse[0, 0, 0] and coarse.sum() == 1
    with pytest.raises(ValueError, match="must divide"):
        downsample(grid, 3)


def test_downsampled_ball_keeps_its_volume_at_any_output_resolution() -> None:
    fine64, fine256 = _ball(64), _ball(256)
    coarse64, coarse256 = downsample(fine64, 32), downsample(fine256, 32)
    for fine, coarse in ((fine64, coarse64), (fine256, coarse256)):
        assert coarse.mean() == pytest.approx(fine.mean(), rel=0.03)
    assert iou(coarse64, coarse256) > 0.97  # so IoU at 32^3 compares 64^3 and 256^3 outputs


def test_surface_of_a_solid_cube_is_its_shell() -> None:
    cube = _box((0, 0, 0), (3, 3, 3), n=6)  # touches the grid border: outside counts empty
    points = surface_points(cube, voxel_mm=2.0)
    assert len(points) == 26
    assert not any((p == [2.0, 2.0, 2.0]).all() for p in points)  # the centre voxel
    assert surface_points(np.zeros((6, 6, 6), dtype=bool), 2.0).shape == (0, 3)


def test_point_metrics_unchanged_under_a_rigid_motion() -> None:
    pred, truth = _pair()
    angle = 0.7
    motion = np.eye(4)
    motion[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                      [0, 0, 1]]
    motion[:3, 3] = [120.0, -35.0, 8.0]
    grid_to_world = motion @ np.diag([0.5, 0.5, 0.5, 1.0])
    here = surface_points(pred, 0.5), surface_points(truth, 0.5)
    there = surface_points(pred, 0.5, grid_to_world), surface_points(truth, 0.5, grid_to_world)
    assert chamfer_l1(*there) == pytest.approx(chamfer_l1(*here))
    assert fscore(*there, threshold_mm=0.6) == pytest.approx(fscore(*here, threshold_mm=0.6))
    with pytest.raises(ValueError, match="not voxel_mm"):
        surface_points(pred, 1.0, grid_to_world)


def test_bbox_diagonal_counts_whole_voxels() -> None:
    assert bbox_diagonal(_box((2, 2, 2), (6, 6, 6)), voxel_mm=2.0) == pytest.approx(8 * 3**0.5)
    assert bbox_diagonal(np.zeros((4, 4, 4), dtype=bool), voxel_mm=2.0) == 0.0


def test_part_metrics_of_a_perfect_prediction() -> None:
    _, truth = _pair()
    scores = part_metrics(truth.copy(), truth, voxel_mm=0.5)
    assert list(scores) == list(METRICS)
    assert scores == {**dict.fromkeys(METRICS, 1.0), "composition_error": 0.0, "missing": 0.0,
                      "chamfer_l1": 0.0}


def test_part_metrics_of_an_empty_prediction() -> None:
    _, truth = _pair()
    scores = part_metrics(np.zeros_like(truth), truth, voxel_mm=0.5)
    assert math.isnan(scores["composition_error"])
    # an empty prediction costs the part's size, so it cannot leave the means looking better
    assert scores["chamfer_l1"] == pytest.approx(bbox_diagonal(truth, 0.5))
    assert scores["chamfer_l1"] > 0
    assert {k: scores[k] for k in ("iou", "iou32", "missing", "overlap_xy", "fscore")} == {
        "iou": 0.0, "iou32": 0.0, "missing": 1.0, "overlap_xy": 0.0, "fscore": 0.0}


def test_part_metrics_refuses_an_empty_truth() -> None:
    pred, truth = _pair()
    with pytest.raises(ValueError, match="truth grid is empty"):
        part_metrics(pred, np.zeros_like(truth), voxel_mm=0.5)


def test_fscore_threshold_is_one_percent_of_the_part_size_and_at_least_a_voxel() -> None:
    truth = _box((0, 0, 0), (60, 60, 60), n=64)  # diagonal 60 * sqrt(3) voxels = 1.04 voxels
    shifted = np.roll(truth, 1, axis=0)
    assert part_metrics(shifted, truth, voxel_mm=1.0)["fscore"] > 0.9  # 1 voxel is within
    thin = _box((0, 0, 0), (60, 8, 8), n=64)  # 1% of the diagonal is 0.61 voxel: one voxel
    assert part_metrics(np.roll(thin, 1, axis=1), thin, voxel_mm=1.0)["fscore"] > 0.9
    big = MetricsConfig(fscore_min_voxels=0.0)  # without the floor, one voxel off misses
    assert part_metrics(np.roll(thin, 1, axis=1), thin, 1.0, big)["fscore"] < 0.9
    assert part_metrics(np.roll(thin, 2, axis=1), thin, voxel_mm=1.0)["fscore"] < 0.9
