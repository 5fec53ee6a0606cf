"""Registering a part's CAD to the points a camera saw of it.

Two seeds, as inspection software does it:

- ``refine`` from a given pose (the design pose, once the whole assembly is aligned to the
  scan): point-to-plane ICP with a robust (Tukey) kernel against the CAD surface as the cameras
  would see it at the current pose (``surface.visible``, re-rendered at every scale of the
  correspondence distance, coarse to fine);
- ``global_search``, which never sees the design: FPFH features of the CAD samples and of the
  scan, RANSAC over feature matches with fixed seeds, several hypotheses (more for small parts,
  and each flipped half a turn about its principal axes, the ambiguity a small part's few
  pixels leave), the best few of them ranked again by how much of the part's surface the
  depth does not see through (where a judge is given), each refined as above; the best by
  inlier share of the scan, then by how much of the visible CAD the scan covers, then by the
  inlier RMS.

Every fit carries the point-to-plane Hessian of its last step (``Fit.hessian``): what the
points constrain, from which ``cadio.inspect.uncertainty`` reads the pose's covariance and the
directions the view does not constrain. Everything is millimetres, world frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numba
import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from cadio.inspect.surface import (
    Camera,
    Occluders,
    PartSurface,
    as_cloud,
    visible,
    voxel_down,
)
from cadio.inspect.uncertainty import small_motions
from cadio.records import FloatArray, apply_pose

# open3d's registration module (its stubs ask for arguments its functions default)
_REGISTRATION: Any = o3d.pipelines.registration


@dataclass(frozen=True)
class RegisterConfig:
    """Knobs of registration. Lengths mm."""

    # ICP's correspondence distance at each scale, in voxels of the part (coarse to fine), then
    # ``fine_mm`` (about twice the sensor's noise at 0.6 m: the part's own points, not its
    # neighbours'), and the Tukey kernel's width against it: points farther count for nothing.
    scales: tuple[float, ...] = (4.0, 2.0, 1.0)
    fine_mm: float = 3.0
    tukey: float = 1.0  # kernel width, times the scale's distance
    iterations: int = 20  # per scale
    keep: int = 3  # distinct candidates refined against the visible surface
    # The part's voxel: its diameter over this, within the bounds (the scan's spacing at 0.6 m
    # is about 0.9 mm, the sensor's noise there 1.4 mm).
    voxels_per_diameter: float = 25.0
    voxel_bounds_mm: tuple[float, float] = (0.8, 6.0)
    # Global search: RANSAC runs (each its own seed) for a part of ``reference_mm``; smaller
    # parts get more, in proportion, up to ``max_hypotheses``.
    hypotheses: int = 3
    reference_mm: float = 60.0
    max_hypotheses: int = 4
    ransac_iterations: int = 20_000
    flips: bool = True  # also try each hypothesis turned half a turn about each principal axis
    # Beside the feature matches, orientations spread over all of SO(3) (the cube's 24 turns,
    # then seeded draws), each placed on the scan's centroid: features of a featureless part
    # (a shaft, a ball) under the sensor's noise match nothing, its silhouette still does.
    orientations: int = 48
    coarse_iterations: int = 5  # ICP steps that score a candidate before the best are refined
    coarse_points: int = 300  # scan points that score a candidate (a seeded draw)
    # Of the candidates within ``judged_within`` of the best coarse score, the first
    # ``judged`` are ranked again by how much of the part's surface (``judged_points``
    # samples) the depth does not contradict, where a judge is given (``_judged``).
    judged: int = 24
    judged_within: float = 0.1
    judged_points: int = 500
    # Where the best judged candidate stays under this (the depth contradicts a tenth or more
    # of the part's surface there), the starts from the principal axes are slid along the
    # part's shorter axes too (``_slides``) and all are judged again.
    slide_below: float = 0.9
    # The spread orientations are tried only when no candidate's coarse score (the inlier
    # share of the scan) reaches this.
    good_enough: float = 0.85
    seed: int = 0
    stride: int = 1  # every stride-th pixel of the visible surface
    # At most this many of the scan's points near the part take part (a seeded draw): the
    # sensor's errors are correlated over patches, so more points buy little and cost much.
    max_points: int = 4000
    monotone: bool = False  # ICP keeps a step only where it lowers the robust cost (``_icp``)
    # Each scan point weighs by its depth's inverse variance where its sigma is given
    # (``refine``'s ``sigma``): a view from 0.3 m sees a part with a tenth of the variance of
    # one from 0.6 m. On the development assemblies (intact, all views, the design route) the
    # pose error's 90th percentile fell from 0.31 mm and 1.05 degrees to 0.27 mm and 0.56.
    weighted: bool = True


@dataclass(frozen=True)
class Fit:
    """A part's pose and how well the scan supports it.

    pose: (4, 4) part -> world, mm. fitness: share of the scan points within the finest
    distance of the visible CAD; coverage: share of the visible CAD with a scan point that near;
    rmse_mm: the inliers' point-to-plane RMS (each weighed by its depth's inverse variance
    where the scan's sigmas were given: the RMS of a point of the mean weight); inliers: their
    number; hessian: (6, 6) J^T W J at ``pose``, W those weights (one each without them),
    rotation (radians, about ``centre``) then translation (mm); centre: (3,) the
    part's centroid at ``pose``, world mm; visible: CAD points the cameras see at ``pose``;
    seen: those points (at the fit's stride; None where it saw none).
    """

    pose: FloatArray
    fitness: float
    coverage: float
    rmse_mm: float
    inliers: int
    hessian: FloatArray
    centre: FloatArray
    visible: int
    seed: str = ""
    consistent: float = 1.0  # the share of the visible CAD the depth does not contradict
    seen: FloatArray | None = field(default=None, repr=False, compare=False)

    def rank(self) -> tuple[float, float, float]:
        """Larger is better: the share of the scan it explains times the share of its
        visible CAD the depth does not contradict (a small segment fits inside a large part,
        whose other faces the depth then contradicts), the coverage of the CAD, then -RMS."""
        return (round(self.fitness * self.consistent, 2), round(self.coverage, 2),
                -settled(self.rmse_mm))


def settled(value: float) -> float:
    """A figure that breaks a tie between candidates (an RMS, a distance), to a micrometre:
    two candidates whose figures differ only in their last bits (the order of a sum, the
    memory alignment a vector kernel met) tie, and the first in their fixed order wins, so that
    a run's answer does not depend on what its process did before."""
    return round(value, 6)


def voxel_of(part: PartSurface, cfg: RegisterConfig) -> float:
    lo, hi = cfg.voxel_bounds_mm
    return float(np.clip(part.diameter / cfg.voxels_per_diameter, lo, hi))


Judge = Callable[[FloatArray], float]  # a hypothesis's visible CAD points -> consistency


def refine(part: PartSurface, scan: FloatArray, pose: FloatArray, cameras: Sequence[Camera],
           cfg: RegisterConfig = RegisterConfig(),
           hidden_by: tuple[Occluders, int] | None = None, judge: Judge | None = None,
           sigma: FloatArray | None = None) -> Fit:
    """Point-to-plane ICP of the part from ``pose`` onto ``scan`` (n, 3) world mm, coarse to
    fine, against what the cameras see of it (re-rendered at each scale). Only the scan's
    points within the part's reach of its place take part. ``sigma``: (n,) each point's depth
    standard deviation (mm, ``scan.Scan.sigma``): a point weighs by its inverse square in
    every step and in the fit's RMS and Hessian, so that a view from near counts for what it
    sees better (None: every point alike).

    Raises:
        ValueError: an empty scan.
    """
    if len(scan) == 0:
        raise ValueError("registration needs scan points")
    current = np.asarray(pose, dtype=np.float64)
    steps = reaches(part, cfg) if cfg.scales else [cfg.fine_mm]
    # (with ``hidden_by``, what the other parts where they stand hide of it is no target)
    centre, radius = apply_pose(current, part.centre), part.diameter / 2 + steps[0]
    chosen = _draw(np.flatnonzero(np.sum((scan - centre) ** 2, axis=1) <= radius * radius),
                   cfg.max_points, cfg.seed)
    near = scan[chosen]
    weight = None if sigma is None or not cfg.weighted else \
        _weights(np.asarray(sigma)[chosen])
    for reach in steps:
        model, normals = visible(part, current, cameras, cfg.stride, hidden_by)
        if len(model) < 6:
            break
        current = _icp(model, normals, near, current, apply_pose(current, part.centre), reach,
                       cfg, weight)
    return _scored(part, near, current, cameras, cfg, hidden_by, judge, weight)


def _weights(sigma: FloatArray) -> FloatArray | None:
    """Each point's weight from its depth sigma: the inverse variance, over its mean (a
    point of the mean sigma weighs about one); None where there is no point."""
    if not len(sigma):
        return None
    inverse = 1.0 / np.maximum(sigma, 1e-3) ** 2
    out: FloatArray = inverse / inverse.mean()
    return out


def _draw(points: NDArray[Any], n: int, seed: int) -> NDArray[Any]:
    """At most n of the points (or indices), drawn without repeats (seeded)."""
    if len(points) <= n:
        return points
    chosen = np.sort(np.random.default_rng(seed).choice(len(points), n, replace=False))
    out: NDArray[Any] = points[chosen]
    return out


def _icp(model: FloatArray, normals: FloatArray, scan: FloatArray, pose: FloatArray,
         centre: FloatArray, reach: float, cfg: RegisterConfig,
         weight: FloatArray | None = None) -> FloatArray:
    """``cfg.iterations`` Gauss-Newton steps at one scale. The visible CAD stays put (one
    tree) and the scan moves by each step's inverse; the part's pose takes the steps.
    ``weight``: (n,) each scan point's weight (``_weights``; None: one each).

    With ``cfg.monotone`` a step is kept only where it lowers the robust cost of the points
    paired before it (``_steps``' cost, those points paired again wherever they now lie
    nearest, so that no point's leaving the pairing distance makes a step look cheaper); ICP
    stops at the first that does not. From a part's place in the design (``by_design``),
    unchecked steps under the sensor's correlated noise walk a small part along a direction
    its points hardly hold: a nut of the held-out flange, refined from where it stood, came out
    3.2 mm and 27 degrees off with its fit worse there (0.36 mm and 4 degrees checked). From
    far (the search's scales) the cost of a sparse visible surface is too rough a guide."""
    cad = _Cad(model, normals, KDTree(model))
    moved = scan
    total = np.eye(4)
    kept = (moved, total)
    before, paired = math.inf, None
    for done in range(cfg.iterations + int(cfg.monotone)):
        step = _steps(cad, moved[None], centre, reach, cfg.tukey * reach,
                      paired if cfg.monotone else None, None if weight is None else weight[None])
        if cfg.monotone and step.among[0] >= before:
            moved, total = kept  # the last step made it worse: undo it
            break
        before, paired, kept = float(step.cost[0]), step.paired, (moved, total)
        if not step.ok[0] or done == cfg.iterations:  # (a last pass only checks the last step)
            break
        motion = step.steps[0]
        total = total @ motion  # (each step is taken where the last left the part)
        moved = apply_pose(np.asarray(np.linalg.inv(motion), dtype=np.float64), moved)
        if np.linalg.norm(motion[:3, 3]) < 1e-4 and abs(np.trace(motion[:3, :3]) - 3) < 1e-9:
            break
    # the scan moved by total^-1 against the part: the part moves by total
    out: FloatArray = total @ pose
    return out


def reaches(part: PartSurface, cfg: RegisterConfig) -> list[float]:
    """The correspondence distances of ICP's scales, mm, coarse to fine."""
    voxel = voxel_of(part, cfg)
    return [*(s * voxel for s in cfg.scales if s * voxel > cfg.fine_mm), cfg.fine_mm]


def _scored(part: PartSurface, scan: FloatArray, pose: FloatArray,
            cameras: Sequence[Camera], cfg: RegisterConfig,
            hidden_by: tuple[Occluders, int] | None = None, judge: Judge | None = None,
            weight: FloatArray | None = None) -> Fit:
    """The fit at ``pose``: fitness and coverage at the finest distance, RMS, Hessian (each
    inlier weighed by ``weight``, over its mean among them: the RMS of a point of the mean
    weight)."""
    reach = cfg.fine_mm
    tree = KDTree(scan) if len(scan) else None
    model, normals = visible(part, pose, cameras, cfg.stride, hidden_by)
    centre = apply_pose(pose, part.centre)
    if len(model) < 6:
        return Fit(pose, 0.0, 0.0, float("inf"), 0, np.zeros((6, 6)), centre, len(model))
    near = seen_tree(model)
    dist, idx = near.query(scan, distance_upper_bound=reach)
    keep = np.isfinite(dist)
    covered = tree.query(model, distance_upper_bound=reach)[0] if tree is not None else \
        np.full(len(model), np.inf)
    if keep.sum() < 6:
        return Fit(pose, 0.0, float(np.isfinite(covered).mean()), float("inf"), int(keep.sum()),
                   np.zeros((6, 6)), centre, len(model))
    s, m, n = scan[keep], model[idx[keep]], normals[idx[keep]]
    r = np.einsum("ij,ij->i", n, m - s)
    jac = np.hstack([np.cross(m - centre, n), n])
    w = np.ones(len(r)) if weight is None else weight[keep] / weight[keep].mean()
    return Fit(pose, float(keep.mean()), float(np.isfinite(covered).mean()),
               float(np.sqrt(np.mean(w * r ** 2))), int(keep.sum()),
               (jac * w[:, None]).T @ jac, centre,
               len(model), consistent=judge(model) if judge is not None else 1.0, seen=model)


# ---------------------------------------------------------------- global search


@dataclass(frozen=True, eq=False)
class _Features:
    cloud: Any
    fpfh: Any
    points: FloatArray = field(repr=False)


def _features(points: FloatArray, normals: FloatArray | None, voxel: float,
              towards: FloatArray | None = None) -> _Features:
    """FPFH of a cloud downsampled to ``voxel``; normals estimated where not given (turned
    towards ``towards``, the camera, for a scan)."""
    cloud = as_cloud(points, normals).voxel_down_sample(voxel)
    if normals is None:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel,
                                                                    max_nn=30))
        if towards is not None:
            cloud.orient_normals_towards_camera_location(towards)
    fpfh = _REGISTRATION.compute_fpfh_feature(
        cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
    return _Features(cloud, fpfh, np.asarray(cloud.points))


_MODEL_FEATURES: dict[tuple[str, float], _Features] = {}


def _model_features(part: PartSurface, voxel: float) -> _Features:
    """A part's CAD features at a voxel, computed once per part and voxel."""
    key = (f"{part.part_id}:{part.diameter:.6f}:{len(part.samples)}", voxel)
    if key not in _MODEL_FEATURES:
        if len(_MODEL_FEATURES) > 256:
            _MODEL_FEATURES.clear()
        _MODEL_FEATURES[key] = _features(part.samples, part.normals, voxel)
    return _MODEL_FEATURES[key]


def hypotheses_for(part: PartSurface, cfg: RegisterConfig) -> int:
    """RANSAC runs for a part: more where it is small (its few pixels leave more ambiguity)."""
    scale = cfg.reference_mm / max(part.diameter, 1e-6)
    return int(np.clip(round(cfg.hypotheses * max(1.0, scale)), cfg.hypotheses,
                       cfg.max_hypotheses))


def global_search(part: PartSurface, scan: FloatArray, cameras: Sequence[Camera],
                  cfg: RegisterConfig = RegisterConfig(), judge: Judge | None = None,
                  sigma: FloatArray | None = None) -> list[Fit]:
    """The part's poses in the scan found without any prior pose, best first: candidates from
    feature matches (FPFH, RANSAC, each also flipped about the part's principal axes) and from
    the scan's principal axes turned onto the part's, each scored after a few coarse ICP steps
    against the whole CAD surface (cheap: no rendering); orientations spread over SO(3) only
    where none of those fits well; the best ``keep`` refined against the visible surface.

    Raises:
        ValueError: fewer than ten scan points.
    """
    if len(scan) < 10:
        raise ValueError("registration needs scan points")
    voxel = voxel_of(part, cfg)
    reach = max(cfg.scales[0] * voxel, cfg.fine_mm)
    few = _draw(scan, cfg.coarse_points, cfg.seed)
    towards = np.mean([c.centre for c in cameras], axis=0)
    starts = [(pose, f"ransac-{k}")
              for k, start in enumerate(_ransac(part, scan, cameras, cfg, voxel))
              for pose in (_with_flips(part, start) if cfg.flips else [start])]
    scored = [(*fit, seed) for fit, (_, seed) in
              zip(_coarse(part, few, [p for p, _ in starts], reach, cfg), starts, strict=True)]
    turns = _principal_turns(part, scan)
    if not any(score[0] >= cfg.good_enough for score, _, _ in scored):
        turns += _orientations(cfg.orientations, cfg.seed)[24:]
    facing = [_facing(part, rot, scan.mean(axis=0), towards) for rot in turns]
    starts = [(start, f"turn-{k}") for k, pose in enumerate(facing)
              for start in _slides(part, pose, scan)]
    scored += [(*fit, seed) for fit, (_, seed) in
               zip(_coarse(part, few, [p for p, _ in starts], reach, cfg), starts, strict=True)]
    scored.sort(key=lambda item: item[0], reverse=True)
    if judge is not None and cfg.judged:
        judged = _judged(part, scored, judge, cfg)
        if judged and judged[0][0][0] < cfg.slide_below:
            starts = [(start, f"turn-{k}") for k, pose in enumerate(facing)
                      for start in _slides(part, pose, scan, axes=(1, 0))[1:]]
            scored += [(*fit, seed) for fit, (_, seed) in
                       zip(_coarse(part, few, [p for p, _ in starts], reach, cfg), starts,
                           strict=True)]
            scored.sort(key=lambda item: item[0], reverse=True)  # stable: the first starts first
            judged = _judged(part, scored, judge, cfg)
        scored = judged
    best = _distinct(scored, part.diameter / 10, cfg.keep)
    return sorted((replace(refine(part, scan, pose, cameras, cfg, judge=judge, sigma=sigma),
                           seed=seed)
                   for pose, seed in best), key=Fit.rank, reverse=True)


def _judged(part: PartSurface, scored: list[tuple[tuple[float, float], FloatArray, str]],
            judge: Judge, cfg: RegisterConfig
            ) -> list[tuple[tuple[float, float], FloatArray, str]]:
    """The ranked candidates with the best few (within ``judged_within`` of the best inlier
    share, ``judged`` at most) ranked again by that share times how much of the part's
    surface at the candidate's pose the depth does not contradict: a cylinder that shows a
    short stretch of itself fits it anywhere along its length, and only where the rest of it
    lies hidden is the depth not seen through it."""
    if not scored:
        return scored
    top = scored[0][0][0]
    head = [item for item in scored[:cfg.judged] if item[0][0] >= top - cfg.judged_within]
    samples = part.samples[::max(1, len(part.samples) // cfg.judged_points)]
    rescored = [((round(score[0] * judge(apply_pose(pose, samples)), 2), score[1]), pose, seed)
                for score, pose, seed in head]
    rescored.sort(key=lambda item: item[0], reverse=True)
    return rescored + scored[len(head):]


def coarse_scores(part: PartSurface, scan: FloatArray, poses: Sequence[FloatArray],
                  cfg: RegisterConfig = RegisterConfig()
                  ) -> list[tuple[tuple[float, float], FloatArray]]:
    """Each pose after the search's few coarse ICP steps against the part's whole surface,
    with the score ``global_search`` ranks its candidates by: the share of (a seeded draw of)
    the scan within half the coarse reach, then -RMS."""
    reach = max(cfg.scales[0] * voxel_of(part, cfg), cfg.fine_mm)
    return _coarse(part, _draw(scan, cfg.coarse_points, cfg.seed), poses, reach, cfg)


def _distinct(scored: Sequence[tuple[tuple[float, float], FloatArray, str]], apart_mm: float,
              n: int) -> list[tuple[FloatArray, str]]:
    """The first n poses of a ranked list that differ from every earlier one by more than
    ``apart_mm`` at the part's rim (or a tenth of a turn)."""
    out: list[tuple[FloatArray, str]] = []
    for _, pose, seed in scored:
        if all(np.linalg.norm(pose[:3, 3] - kept[:3, 3]) > apart_mm
               or np.trace(pose[:3, :3].T @ kept[:3, :3]) < 1 + 2 * np.cos(0.1 * np.pi)
               for kept, _ in out):
            out.append((pose, seed))
        if len(out) == n:
            break
    return out


# The trees of the last few visible surfaces a fit was scored on (``_scored``), by the array:
# the route that placed the part reads the same points again (``routes._explained``), and a
# large part's visible CAD (hundreds of thousands of points) takes tens of milliseconds to
# build a tree of.
_SEEN_TREES: list[tuple[FloatArray, KDTree]] = []


def seen_tree(points: FloatArray) -> KDTree:
    """The k-d tree of ``points`` (a fit's visible CAD), built once while it is recent."""
    for kept, tree in _SEEN_TREES:
        if kept is points:
            return tree
    tree = KDTree(points)
    _SEEN_TREES.insert(0, (points, tree))
    del _SEEN_TREES[4:]
    return tree


_TREES: dict[int, tuple[PartSurface, KDTree]] = {}


def _tree(part: PartSurface) -> KDTree:
    """The k-d tree of a part's samples in its own frame, built once per part."""
    cached = _TREES.get(id(part))
    if cached is None or cached[0] is not part:
        if len(_TREES) > 512:
            _TREES.clear()
        cached = (part, KDTree(part.samples))
        _TREES[id(part)] = cached
    return cached[1]


def _coarse(part: PartSurface, scan: FloatArray, poses: Sequence[FloatArray], reach: float,
            cfg: RegisterConfig) -> list[tuple[tuple[float, float], FloatArray]]:
    """Candidates after ``coarse_iterations`` point-to-plane steps against the part's whole
    surface (in its own frame, the scan brought there), each with its score: the share of the
    scan within ``reach / 2`` of the surface, then -RMS. All candidates step together (one
    tree query and one batch of 6x6 solves per step); a candidate without enough pairs stops
    where it is."""
    if not poses:
        return []
    tree = _tree(part)
    cad = _Cad(part.samples, part.normals, tree)
    starts = np.stack([np.asarray(p, dtype=np.float64) for p in poses])
    inverse = np.linalg.inv(starts)
    moved = np.einsum("kij,nj->kni", inverse[:, :3, :3], scan) + inverse[:, None, :3, 3]
    total = np.tile(np.eye(4), (len(starts), 1, 1))
    going = np.ones(len(starts), dtype=bool)
    for _ in range(cfg.coarse_iterations):
        if not going.any():
            break
        step = _steps(cad, moved[going], part.centre, reach, cfg.tukey * reach)
        steps, ok = step.steps, step.ok
        index = np.flatnonzero(going)
        going[index[~ok]] = False
        index, steps = index[ok], steps[ok]
        total[index] = total[index] @ steps
        back = np.linalg.inv(steps)
        moved[index] = (np.einsum("kij,knj->kni", back[:, :3, :3], moved[index])
                        + back[:, None, :3, 3])
    dist, _ = tree.query(moved.reshape(-1, 3), distance_upper_bound=reach / 2)
    dist = dist.reshape(len(starts), -1)
    near = np.isfinite(dist)
    count = near.sum(axis=1)
    squares = np.where(near, dist, 0.0) ** 2
    rms = np.where(count > 0, np.sqrt(squares.sum(axis=1) / np.maximum(count, 1)), np.inf)
    out: list[tuple[tuple[float, float], FloatArray]] = []
    for k in range(len(starts)):
        pose: FloatArray = starts[k] @ total[k]
        out.append(((round(float(count[k] / moved.shape[1]), 2), -settled(float(rms[k]))), pose))
    return out


@dataclass(frozen=True, eq=False)
class _Step:
    """One Gauss-Newton step of k candidates (``_steps``): steps (k, 4, 4); ok (k,): the
    candidate had enough pairs (six; the others' steps are the identity); cost (k,): the
    robust cost of its pairs where it stands (Tukey's rho of each point-to-plane residual,
    a paired point past the kernel costing its most); paired (k, n): its points within the
    pairing distance; among (k,): the cost of the points ``among`` paired, each with its
    nearest CAD point now (one farther than twice the pairing distance costing its most)."""

    steps: FloatArray
    ok: NDArray[np.bool_]
    cost: FloatArray
    paired: NDArray[np.bool_]
    among: FloatArray


@dataclass(frozen=True, eq=False)
class _Cad:
    """The CAD points a scan is paired with, their normals and their tree."""

    points: FloatArray
    normals: FloatArray
    tree: KDTree


def _steps(cad: _Cad, scans: FloatArray, centre: FloatArray, reach: float, kernel: float,
           among: NDArray[np.bool_] | None = None, weight: FloatArray | None = None) -> _Step:
    """One Gauss-Newton step of the part (4, 4, world) for each of k candidates: scans
    (k, n, 3); ``among``: (k, n) the points whose cost to read besides (``_Step.among``);
    ``weight``: (k, n) each point's weight in the step and the costs (None: one each).

    Each scan point is paired with its nearest visible CAD point (a model tree would pair the
    CAD with the scan: the scan holds other parts' points too, the visible CAD only this one's).
    Damped (Levenberg-Marquardt) in units where a turn counts by its motion at the part's rim:
    a direction the points do not constrain (a shaft's turn about its axis) takes no step from
    the noise instead of a wild one; no step moves a point of the part farther than ``reach``.
    """
    k, n = scans.shape[:2]
    # (the points read ``among`` were paired at most one step ago, which moved none of them
    # farther than ``reach``: all lie within twice that of their nearest CAD point)
    dist, idx = cad.tree.query(scans.reshape(-1, 3),
                               distance_upper_bound=reach if among is None else 2 * reach)
    hessian, grad, cost, read, count, spread, keep = _normal_equations(
        np.ascontiguousarray(scans, dtype=np.float64), dist.reshape(k, n),
        idx.reshape(k, n).astype(np.int64), cad.points, cad.normals,
        np.asarray(centre, dtype=np.float64), float(reach), float(kernel),
        np.zeros((0, 0), dtype=np.bool_) if among is None else np.ascontiguousarray(among),
        np.zeros((0, 0)) if weight is None else np.ascontiguousarray(weight, dtype=np.float64))
    ok = count >= 6
    radius = np.maximum(np.sqrt(spread / np.maximum(count, 1)), 1e-6)
    scale = np.concatenate([np.repeat((1 / radius)[:, None], 3, axis=1), np.ones((k, 3))],
                           axis=1)
    h = hessian * scale[:, :, None] * scale[:, None, :]
    damping = 1e-3 * np.trace(h, axis1=1, axis2=2) / 6 + 1e-12
    h = h + damping[:, None, None] * np.eye(6)
    h[~ok] = np.eye(6)
    try:
        delta = -scale * np.linalg.solve(h, (scale * grad)[..., None])[..., 0]
    except np.linalg.LinAlgError:  # one singular system: solve them one by one
        delta = np.zeros((k, 6))
        for j in np.flatnonzero(ok):
            try:
                delta[j] = -scale[j] * np.linalg.solve(h[j], scale[j] * grad[j])
            except np.linalg.LinAlgError:
                ok[j] = False
    turn = np.linalg.norm(delta[:, :3], axis=1)
    shift = np.linalg.norm(delta[:, 3:], axis=1)
    delta[:, :3] *= np.minimum(1.0, (reach / radius) / np.maximum(turn, 1e-12))[:, None]
    delta[:, 3:] *= np.minimum(1.0, reach / np.maximum(shift, 1e-12))[:, None]
    delta[~ok] = 0.0
    return _Step(small_motions(delta, centre), ok, cost, keep, read)


@numba.njit(nogil=True, cache=True)
def _normal_equations(scans: Any, dist: Any, idx: Any, points: Any,  # noqa: C901, PLR0913
                      normals: Any, centre: Any, reach: float, kernel: float, among: Any,
                      weight: Any) -> Any:
    """``_steps``' sums in one pass over the pairs, without the arrays numpy would make of
    each term: per candidate J^T W J (6, 6), J^T W r (6,), the robust cost of its pairs and of
    the points ``among`` marks (an empty array: none, the cost read twice), its pairs' count
    and squared spread about ``centre``; and which points it paired (``dist`` within
    ``reach``). A point beyond the query's bound (inf) costs Tukey's most; ``weight`` (an
    empty array: one each) scales each point's cost and its terms."""
    k, n = dist.shape
    hessian = np.zeros((k, 6, 6))
    grad = np.zeros((k, 6))
    cost = np.zeros(k)
    read = np.zeros(k)
    count = np.zeros(k, dtype=np.int64)
    spread = np.zeros(k)
    paired = np.zeros((k, n), dtype=np.bool_)
    most = kernel * kernel / 6.0
    jac = np.empty(6)
    for a in range(k):
        for i in range(n):
            wi = weight[a, i] if weight.shape[0] > 0 else 1.0
            marked = among.shape[0] > 0 and among[a, i]
            d = dist[a, i]
            if not np.isfinite(d):
                if marked:
                    read[a] += most * wi
                continue
            j = idx[a, i]
            mx, my, mz = points[j, 0], points[j, 1], points[j, 2]
            nx, ny, nz = normals[j, 0], normals[j, 1], normals[j, 2]
            r = nx * (mx - scans[a, i, 0]) + ny * (my - scans[a, i, 1]) \
                + nz * (mz - scans[a, i, 2])
            inside = abs(r) < kernel
            t = 1.0 - (r / kernel) ** 2
            rho = ((1.0 - t * t * t) if inside else 1.0) * most * wi
            if marked:
                read[a] += rho
            if d > reach:
                continue
            paired[a, i] = True
            cost[a] += rho
            count[a] += 1
            px, py, pz = mx - centre[0], my - centre[1], mz - centre[2]
            spread[a] += px * px + py * py + pz * pz
            if not inside:
                continue
            w = t * t * wi
            jac[0], jac[1], jac[2] = py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx
            jac[3], jac[4], jac[5] = nx, ny, nz
            for p in range(6):
                wp = w * jac[p]
                grad[a, p] += wp * r
                for q in range(p, 6):
                    hessian[a, p, q] += wp * jac[q]
        for p in range(6):
            for q in range(p):
                hessian[a, p, q] = hessian[a, q, p]
    if among.shape[0] == 0:
        read[:] = cost
    return hessian, grad, cost, read, count, spread, paired


def _ransac(part: PartSurface, scan: FloatArray, cameras: Sequence[Camera],
            cfg: RegisterConfig, voxel: float) -> list[FloatArray]:
    """Poses from RANSAC over FPFH matches, one per seed (none where the features match
    nothing)."""
    model = _model_features(part, voxel)
    towards = np.mean([c.centre for c in cameras], axis=0)
    seen = _features(voxel_down(scan, 0.5 * voxel), None, voxel, towards)
    out = []
    for k in range(hypotheses_for(part, cfg)):
        o3d.utility.random.seed(cfg.seed * 7919 + k)
        found = o3d.pipelines.registration.registration_ransac_based_on_feature_matching(
            model.cloud, seen.cloud, model.fpfh, seen.fpfh, False, 1.5 * voxel,
            o3d.pipelines.registration.TransformationEstimationPointToPoint(False), 3,
            [o3d.pipelines.registration.CorrespondenceCheckerBasedOnEdgeLength(0.9),
             o3d.pipelines.registration.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            o3d.pipelines.registration.RANSACConvergenceCriteria(cfg.ransac_iterations, 0.999))
        if found.fitness > 0:
            out.append(np.asarray(found.transformation, dtype=np.float64))
    return out


def align_samples(part: PartSurface, other: PartSurface) -> FloatArray:
    """(4, 4) the motion of ``part``'s frame that lays its samples best on ``other``'s surface
    (two parts of one shape): of the 24 turns putting principal axes on principal axes, the
    one of least RMS after ICP against ``other``'s whole surface. The turns are told apart
    after a few steps on a few samples, and the best two of them finished on more: all 24 on
    2,000 samples to the end took seconds a pair (a bearing's 31 balls, a minute)."""
    reach = max(other.diameter / 10, 1.0)
    starts = []
    for rot in _principal_turns(other, part.samples):
        start = np.eye(4)  # other's frame -> part's frame, as a pose of other in part's
        start[:3, :3] = rot
        start[:3, 3] = part.centre - rot @ other.centre
        starts.append(start)
    tried = _coarse(other, _draw(part.samples, 500, 0), starts, reach,
                    RegisterConfig(coarse_iterations=10))
    order = sorted(range(len(tried)), key=lambda k: tried[k][0], reverse=True)  # stable
    scored = _coarse(other, _draw(part.samples, 2000, 0), [tried[k][1] for k in order[:2]],
                     reach, RegisterConfig(coarse_iterations=30))
    best = max(range(len(scored)), key=lambda k: scored[k][0])  # the first of the best
    out: FloatArray = np.asarray(np.linalg.inv(scored[best][1]), dtype=np.float64)
    return out


def _principal_turns(part: PartSurface, scan: FloatArray) -> list[FloatArray]:
    """The 24 turns that put the part's principal axes on the scan's (every order and sign)."""
    _, seen_axes = np.linalg.eigh(np.cov((scan - scan.mean(axis=0)).T))
    _, part_axes = np.linalg.eigh(np.cov((part.samples - part.centre).T))
    turns = [seen_axes @ cube @ part_axes.T for cube in _orientations(24, 0)]
    return [t if np.linalg.det(t) > 0 else t @ np.diag([1.0, 1.0, -1.0]) for t in turns]


def _facing(part: PartSurface, rot: FloatArray, target: FloatArray, towards: FloatArray
            ) -> FloatArray:
    """(4, 4) the part turned by ``rot`` and moved so that the mean of its samples facing
    ``towards`` (the cameras: what they would see of it) lies on ``target``. (A sample faces
    a point where its normal turned by ``rot`` points towards it: n . (rot^T (towards - t))
    exceeds n . s, read in the part's frame without moving its samples.)"""
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = target - rot @ part.centre
    facing = part.normals @ (rot.T @ (towards - pose[:3, 3])) > part.normal_offsets
    if facing.any():
        pose[:3, 3] += target - (rot @ part.samples[facing].mean(axis=0) + pose[:3, 3])
    return pose


def _slides(part: PartSurface, pose: FloatArray, scan: FloatArray, axes: Sequence[int] = (2,)
            ) -> list[FloatArray]:
    """The pose, and the pose slid both ways along each of the part's principal ``axes``
    (0-2, shortest to longest) by what the part is longer than the scan along it, where that is
    a tenth of its diameter or more. Along its longest: a bolt whose shank the plates hide
    shows its head or its end, which the coarse steps could not find alone; along its shorter
    ones, where no start fits well (``global_search``): a nut under a washer shows a band of its
    flats, which fits it at either end of its axis, and only the depth, which the judge reads,
    says where the rest of it hides."""
    out = [pose]
    for axis in (pose[:3, :3] @ part.principal_axes[:, list(axes)]).T:
        along = (apply_pose(pose, part.samples[::10]) - pose[:3, 3]) @ axis
        seen = scan @ axis
        spare = (np.ptp(along) - (np.percentile(seen, 99) - np.percentile(seen, 1))) / 2
        if spare < 0.1 * part.diameter:
            continue
        for sign in (-1.0, 1.0):
            slid = pose.copy()
            slid[:3, 3] += sign * spare * axis
            out.append(slid)
    return out


def _orientations(n: int, seed: int) -> list[FloatArray]:
    """The 24 turns of the cube, then seeded uniform draws, n in all."""
    cube = []
    for perm in ((0, 1, 2), (1, 2, 0), (2, 0, 1), (1, 0, 2), (0, 2, 1), (2, 1, 0)):
        for signs in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1),
                      (-1, 1, 1), (1, -1, 1), (1, 1, -1), (-1, -1, -1)):
            m = np.zeros((3, 3))
            m[range(3), perm] = signs
            if np.linalg.det(m) > 0:
                cube.append(m)
    rng = np.random.default_rng(seed)
    while len(cube) < n:
        q = rng.standard_normal(4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        cube.append(np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                              [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                              [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]))
    return cube[:n]


def _with_flips(part: PartSurface, pose: FloatArray) -> list[FloatArray]:
    """The pose, and the pose turned half a turn about each principal axis of the part's
    samples through its centroid."""
    centred = part.samples - part.centre
    _, vectors = np.linalg.eigh(centred.T @ centred)
    out = [pose]
    for axis in vectors.T:
        flip = np.eye(4)
        flip[:3, :3] = 2 * np.outer(axis, axis) - np.eye(3)  # half a turn about ``axis``
        flip[:3, 3] = part.centre - flip[:3, :3] @ part.centre
        out.append(pose @ flip)
    return out
