"""How well a completed part agrees with its CAD truth: metrics on boolean occupancy grids.

Both grids describe one part in one grid: ``(n, n, n)`` bool, indexed ``[i, j, k]`` along x, y,
z (as ``cadio.records.VoxelGrid``), voxel edge ``voxel_mm``. The paper (section III.A) defines
IoU precisely and composition error, missing voxels and projection overlap only loosely; each
function below states the definition used here, so that every number in the report has one
meaning. Point metrics (Chamfer distance, F-score) use the centres of surface voxels, in mm.

A value that is undefined for a part (the composition error or the Chamfer distance of an empty
prediction) is NaN, never a made-up number; ``reports.completion`` leaves NaN out of its means
and counts it. Pure numpy and scipy: no CAD kernel, no torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

BoolGrid = npt.NDArray[np.bool_]
Points = npt.NDArray[np.float64]

# The metrics of one prediction, in the order of the report files' columns.
METRICS = ("iou", "iou32", "composition_error", "missing", "overlap_xy", "overlap_yz",
           "overlap_zx", "chamfer_l1", "fscore")
# Plane of a projection -> the grid axis projected away.
PLANE_AXIS = {"xy": 2, "yz": 0, "zx": 1}


@dataclass(frozen=True)
class MetricsConfig:
    """The two conventions of ``part_metrics``."""

    # IoU is also reported at 32^3, where 64^3 and 256^3 outputs compare (see ``downsample``).
    coarse_n: int = 32
    # F-score threshold as a fraction of the part's size (the truth's bounding-box diagonal),
    # but never under ``fscore_min_voxels`` voxel edges: 1% of the diagonal is under one voxel
    # at 64^3, where the F-score would only count surface voxels that coincide exactly.
    fscore_fraction: float = 0.01
    fscore_min_voxels: float = 1.0


DEFAULT_METRICS_CONFIG = MetricsConfig()


def _check_pair(pred: BoolGrid, truth: BoolGrid) -> None:
    if pred.shape != truth.shape:
        raise ValueError(f"prediction {pred.shape} and truth {truth.shape} differ in shape")
    if pred.dtype != np.bool_ or truth.dtype != np.bool_:
        raise ValueError(f"occupancy must be bool, not {pred.dtype} and {truth.dtype}: "
                         "threshold predicted probabilities before scoring")


def _check_grid(grid: BoolGrid) -> int:
    if grid.ndim != 3 or len(set(grid.shape)) != 1:
        raise ValueError(f"expected a cubic (n, n, n) grid, got shape {grid.shape}")
    return int(grid.shape[0])


def iou(pred: BoolGrid, truth: BoolGrid) -> float:
    """Intersection over union of two occupancies of any equal shape.

    IoU = |p & t| / |p | t|, counted in cells (voxels, or pixels of a silhouette); 1.0 when
    both are empty (two empty shapes agree). The paper's formula with its threshold already
    applied: predictions are bool here.

    Raises:
        ValueError: the shapes differ or either array is not bool.
    """
    _check_pair(pred, truth)
    union = np.count_nonzero(pred | truth)
    return 1.0 if union == 0 else np.count_nonzero(pred & truth) / union


def downsample(grid: BoolGrid, n: int) -> BoolGrid:
    """Occupancy of ``grid`` on a coarser cubic grid of ``n`` cells a side, by majority.

    A coarse voxel is occupied when at least half of the fine voxels inside it are (a value
    exactly at the threshold counts as inside, as every tolerance of the project does).
    Majority, not "any": the share of occupied fine voxels estimates the solid's volume fraction
    of the coarse voxel whatever the fine resolution, so 64^3 and 256^3 outputs of one shape
    give nearly the same 32^3 grid and IoU at 32^3 compares them. "Any" dilates by up to a
    coarse voxel, more so the finer the grid (a 256^3 grid sees walls a 64^3 one misses), and
    hides boundary errors. The price: features thinner than half a coarse voxel vanish.

    Args:
        grid: (m, m, m) bool, with m a multiple of n.
        n: cells a side of the result.
    Returns:
        (n, n, n) bool.
    Raises:
        ValueError: the grid is not cubic or n does not divide its side.
    """
    size = _check_grid(grid)
    if n < 1 or size % n:
        raise ValueError(f"cannot downsample a {size}^3 grid to {n}^3: {n} must divide {size}")
    f = size // n
    if f == 1:
        return np.array(grid, dtype=np.bool_)
    # the fine voxels of each coarse one summed as small integers, one offset in the block at a
    # time: 0.19 ms for 64^3 to 32^3, where count_nonzero over the block's axes took 2.6 ms
    cells = grid.view(np.uint8).reshape(n, f, n, f, n, f)
    counts = np.zeros((n, n, n), dtype=np.uint16 if f**3 < 2**16 else np.int64)
    for i in range(f):
        for j in range(f):
            for k in range(f):
                counts += cells[:, i, :, j, :, k]
    return np.asarray(2 * counts.astype(np.int64) >= f**3)


def composition_error(pred: BoolGrid, truth: BoolGrid) -> float:
    """Share of the predicted voxels that the truth does not hold: |p & ~t| / |p|.

    The paper's "composition error" (voxels composed where there is no solid), normalised by
    the prediction so that it lies in [0, 1] and equals 1 - precision; with ``missing`` it
    determines IoU: 1 / IoU = 1 / (1 - composition_error) + 1 / (1 - missing) - 1.
    NaN for an empty prediction (nothing composed: the share is undefined).
    """
    _check_pair(pred, truth)
    composed = np.count_nonzero(pred)
    return np.nan if composed == 0 else np.count_nonzero(pred & ~truth) / composed


def missing(pred: BoolGrid, truth: BoolGrid) -> float:
    """Share of the truth's voxels that the prediction misses: |~p & t| / |t|.

    The paper's "missing voxels", normalised by the truth so that parts of any size compare:
    1 - recall, in [0, 1] (1.0 for an empty prediction). NaN for an empty truth.
    """
    _check_pair(pred, truth)
    solid = np.count_nonzero(truth)
    return np.nan if solid == 0 else np.count_nonzero(~pred & truth) / solid


def projection_overlap(pred: BoolGrid, truth: BoolGrid, plane: str) -> float:
    """IoU of the two silhouettes of an orthographic projection onto ``plane``.

    A silhouette pixel is occupied when any voxel along the projection axis is: "xy" projects
    along z, "yz" along x, "zx" along y. The paper's Table I reports "projection overlap" on
    these planes without a formula; the IoU of the silhouettes is the reading used here
    (1.0 when both silhouettes are empty).

    Raises:
        ValueError: an unknown plane, or grids that ``iou`` refuses.
    """
    if plane not in PLANE_AXIS:
        raise ValueError(f"unknown plane {plane!r}; known: {', '.join(PLANE_AXIS)}")
    _check_grid(pred)
    axis = PLANE_AXIS[plane]
    return iou(np.any(pred, axis=axis), np.any(truth, axis=axis))


def surface_points(grid: BoolGrid, voxel_mm: float,
                   grid_to_world: npt.NDArray[np.float64] | None = None) -> Points:
    """Centres of the surface voxels: occupied voxels with at least one empty 6-neighbour.

    Voxels on the grid's border count their outside neighbour as empty.

    Args:
        grid: (n, n, n) bool.
        voxel_mm: voxel edge, mm.
        grid_to_world: (4, 4) float64 mapping homogeneous (i, j, k, 1) to the voxel's centre
            in mm, as ``VoxelGrid.grid_to_part`` (so its axes are ``voxel_mm`` long); None puts
            the centre of voxel (i, j, k) at (i, j, k) * voxel_mm.
    Returns:
        (m, 3) float64, mm, in the order of ``np.argwhere``.
    Raises:
        ValueError: a non-cubic grid, or a transform whose scale is not ``voxel_mm``.
    """
    _check_grid(grid)
    transform = _grid_transform(voxel_mm, grid_to_world)
    ijk = np.argwhere(grid & ~_interior(grid)).astype(np.float64)
    return np.asarray(ijk @ transform[:3, :3].T + transform[:3, 3], dtype=np.float64)


def _grid_transform(voxel_mm: float,
                    grid_to_world: npt.NDArray[np.float64] | None) -> npt.NDArray[np.float64]:
    if grid_to_world is None:
        return np.diag([voxel_mm, voxel_mm, voxel_mm, 1.0])
    transform = np.asarray(grid_to_world, dtype=np.float64)
    if transform.shape != (4, 4):
        raise ValueError(f"grid_to_world must be (4, 4), got shape {transform.shape}")
    axes = np.linalg.norm(transform[:3, :3], axis=0)
    if not np.allclose(axes, voxel_mm, rtol=1e-6):
        raise ValueError(f"grid_to_world's axes are {axes} mm long, not voxel_mm = {voxel_mm}")
    return transform


def _interior(grid: BoolGrid) -> BoolGrid:
    """Voxels whose six neighbours are all occupied (outside the grid counts as empty)."""
    padded = np.pad(grid, 1)
    inner = slice(1, -1)
    out = grid.copy()
    for axis in range(3):
        for step in (slice(None, -2), slice(2, None)):
            index = [inner, inner, inner]
            index[axis] = step
            out &= padded[tuple(index)]
    return out


def _check_points(pred_pts: Points, truth_pts: Points) -> None:
    for pts in (pred_pts, truth_pts):
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must be (m, 3), got shape {pts.shape}")


def _point_scores(pred_pts: Points, truth_pts: Points, threshold_mm: float,
                  truth_tree: Any = None) -> tuple[float, float]:
    """(``chamfer_l1``, ``fscore``) from one nearest-neighbour search each way
    (``truth_tree``: the truth points' tree, where the caller built it once for many)."""
    _check_points(pred_pts, truth_pts)
    if len(pred_pts) == 0 or len(truth_pts) == 0:
        return (0.0, 1.0) if len(pred_pts) == len(truth_pts) else (np.nan, 0.0)
    pred_pts, truth_pts = _float64(pred_pts), _float64(truth_pts)
    tree = _tree(truth_pts) if truth_tree is None else truth_tree
    to_truth = np.asarray(tree.query(pred_pts, k=1)[0], dtype=np.float64)
    to_pred = np.asarray(_tree(pred_pts).query(truth_pts, k=1)[0], dtype=np.float64)
    chamfer = float((to_truth.mean() + to_pred.mean()) / 2)
    precision = float(np.mean(to_truth <= threshold_mm))
    recall = float(np.mean(to_pred <= threshold_mm))
    total = precision + recall
    return chamfer, 0.0 if total == 0 else 2 * precision * recall / total


def _tree(points: Points) -> Any:
    """A k-d tree for exact nearest neighbours: pykdtree's, whose nearest distances are
    scipy's cKDTree's (float64, each the root of the same sum of squares), in about half the
    time."""
    # Imported here: reports/ must import in well under a second (STYLE 8) for the tools that
    # only read the report files.
    from pykdtree.kdtree import KDTree

    return KDTree(_float64(points))


def _float64(points: Points) -> Points:
    return np.ascontiguousarray(points, dtype=np.float64)


def chamfer_l1(pred_pts: Points, truth_pts: Points) -> float:
    """Chamfer distance, mm: the mean of the two directed mean nearest-neighbour distances.

    CD = (mean_p min_t |p - t| + mean_t min_p |t - p|) / 2 with Euclidean |.|; "L1" as in the
    completion literature (PCN): distances are not squared, so the value is in millimetres.
    0.0 for two empty sets; NaN when exactly one set is empty (no nearest neighbour).

    Args:
        pred_pts, truth_pts: (m, 3) and (k, 3) float64, mm, in one frame.
    Raises:
        ValueError: an array that is not (m, 3).
    """
    return _point_scores(pred_pts, truth_pts, 0.0)[0]


def fscore(pred_pts: Points, truth_pts: Points, threshold_mm: float) -> float:
    """F-score at a distance threshold: the harmonic mean of precision and recall.

    precision = share of predicted points within ``threshold_mm`` of a truth point, recall =
    share of truth points within ``threshold_mm`` of a predicted point (a distance equal to the
    threshold counts as within); F = 2 P R / (P + R), 0 when P + R = 0. 1.0 for two empty
    sets, 0.0 when exactly one is empty.

    Raises:
        ValueError: an array that is not (m, 3), or a negative threshold.
    """
    if threshold_mm < 0:
        raise ValueError(f"threshold must be non-negative, got {threshold_mm} mm")
    return _point_scores(pred_pts, truth_pts, threshold_mm)[1]


def bbox_diagonal(grid: BoolGrid, voxel_mm: float) -> float:
    """Diagonal, mm, of the axis-aligned box around the occupied voxels' cubes; 0 when empty."""
    _check_grid(grid)
    extent = []
    for axis in range(3):
        occupied = np.flatnonzero(np.any(grid, axis=tuple(a for a in range(3) if a != axis)))
        extent.append(occupied[-1] - occupied[0] + 1 if occupied.size else 0)
    return float(np.linalg.norm(extent) * voxel_mm)


def part_metrics(pred: BoolGrid, truth: BoolGrid, voxel_mm: float,
                 config: MetricsConfig = DEFAULT_METRICS_CONFIG) -> dict[str, float]:
    """Every metric of one prediction against its truth, by the names of ``METRICS``.

    iou at the grids' resolution; iou32 = iou of both grids downsampled to
    ``config.coarse_n`` (unchanged when they are that size already); composition_error,
    missing; overlap_xy/yz/zx = ``projection_overlap``; chamfer_l1 and fscore on the surface
    voxels' centres (mm), the F-score threshold being ``config.fscore_fraction`` times the
    truth's ``bbox_diagonal`` and at least ``config.fscore_min_voxels`` voxel edges. An empty
    prediction scores what it costs: iou 0, missing 1, overlaps 0, fscore 0, chamfer_l1 the
    truth's ``bbox_diagonal`` (no surface point is nearer the truth than the part's size), and
    a NaN composition_error (it is relative to the prediction's own volume).

    Args:
        pred, truth: (n, n, n) bool, one part in one grid; n a multiple of ``coarse_n``.
        voxel_mm: voxel edge, mm.
    Raises:
        ValueError: grids of different shapes or not bool, or an empty truth (nothing to score
            against: the voxelization failed upstream).
    """
    return Truth(truth, voxel_mm, config).metrics(pred)


class Truth:
    """One truth grid, prepared once for scoring many predictions against it (every method
    of an example): its coarse grid, surface points and their tree, size and threshold.

    Raises:
        ValueError: a grid that is not cubic, not bool, or empty.
    """

    def __init__(self, truth: BoolGrid, voxel_mm: float,
                 config: MetricsConfig = DEFAULT_METRICS_CONFIG) -> None:
        _check_grid(truth)
        if truth.dtype != np.bool_:
            raise ValueError(f"occupancy must be bool, not {truth.dtype}")
        if not truth.any():
            raise ValueError("the truth grid is empty: nothing to score the prediction against")
        self.grid, self.voxel_mm, self.config = truth, voxel_mm, config
        self.coarse = downsample(truth, config.coarse_n)
        self.points = surface_points(truth, voxel_mm)
        self.tree = _tree(self.points)
        self.diagonal = bbox_diagonal(truth, voxel_mm)
        self.threshold = max(config.fscore_fraction * self.diagonal,
                             config.fscore_min_voxels * voxel_mm)

    def metrics(self, pred: BoolGrid) -> dict[str, float]:
        """``part_metrics`` of ``pred`` against this truth."""
        truth = self.grid
        _check_pair(pred, truth)
        scores = {
            "iou": iou(pred, truth),
            "iou32": iou(downsample(pred, self.config.coarse_n), self.coarse),
            "composition_error": composition_error(pred, truth),
            "missing": missing(pred, truth),
            **{f"overlap_{p}": projection_overlap(pred, truth, p) for p in PLANE_AXIS},
        }
        scores["chamfer_l1"], scores["fscore"] = _point_scores(
            surface_points(pred, self.voxel_mm), self.points, self.threshold, self.tree)
        if not pred.any():
            scores["chamfer_l1"] = self.diagonal
        return {name: float(scores[name]) for name in METRICS}
