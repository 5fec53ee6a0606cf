"""RANSAC planes and cylinders on a point cloud: the fitting half of the geometric baseline.

``extract`` finds primitives greedily, in the manner of efficient RANSAC (Schnabel et al.
2007): each round proposes planes (a point and its local PCA normal) and cylinders (the axis is
the cross product of two nearby normals, the centre where the two normal lines meet across
it), scores every proposal at once on the points not yet explained, keeps the one with the most
inliers (within the inlier distance, with a normal that agrees), refines it by least squares,
and removes its inliers. ``cadio.capture.primitives`` turns the result into ``Features``.
Everything is in millimetres, in the coordinates of the points given.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial import ConvexHull, QhullError, cKDTree

from cadio.records import FloatArray, perpendicular_pair

log = logging.getLogger(__name__)
IndexArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class PrimitiveConfig:
    """Knobs of the RANSAC primitive fit. Lengths in mm, angles in degrees."""

    seed: int = 0
    # Proposals scored per extraction round. A plane needs one good point (its normal gives the
    # rest), so few suffice; a cylinder needs two points on one cylinder with good normals.
    plane_iterations: int = 64
    cylinder_iterations: int = 128
    # Inlier distance: the largest of a share of the bbox diagonal, a floor, and a multiple of
    # the points' own noise. 1% of the diagonal is 0.6 to 1 voxel of a 64^3 completion grid.
    inlier_fraction: float = 0.01
    inlier_floor_mm: float = 0.05
    # Noise: the median PCA residual of each point's 6 nearest neighbours, about half the depth
    # noise sigma (0.23 mm at sigma 0.5 mm), so 4 of it is about 2 sigma. Wider neighbourhoods
    # straddle both faces of thin plates (10 points: 0.73 mm on a 4 mm voxel plate).
    noise_neighbours: int = 6
    noise_factor: float = 4.0
    # An inlier's normal is within this angle of the primitive's normal there; PCA normals of
    # noisy scans and staircases are off by 10-20 degrees, points on an edge by about 45.
    normal_angle_deg: float = 30.0
    # A primitive explains at least this share of the cloud, and this many points (600-point
    # clouds: 30 points; smaller faces are not told apart from noise).
    min_inlier_share: float = 0.05
    min_inliers: int = 12
    max_primitives: int = 8
    # Neighbours of the local PCA normals, and the wider neighbourhood
    # from which a cylinder proposal takes its second point (whose normal must differ).
    neighbours: int = 10
    cylinder_neighbours: int = 40
    # Proposals whose normals are closer than this give no axis direction worth scoring.
    min_normal_turn_deg: float = 3.0
    # A cylinder wider than this share of the bbox diagonal is a plane strip, not a feature.
    max_radius_fraction: float = 1.0
    # ...and one covering less arc than this is a sliver of something else.
    min_arc_deg: float = 45.0
    arc_bins: int = 24  # arc coverage is counted in bins of 15 degrees
    # The inliers' normals must follow the cylinder: median angle to its radial direction. A box
    # edge, whose PCA normals blend from one face to the other, passes for a fillet by position
    # alone: such fits measured 10-19 degrees, true cylinders 4-6 (surface samples, partial
    # scans with 0.2 mm depth noise, 64^3 voxel surfaces).
    max_cylinder_normal_error_deg: float = 9.0
    # Fitted faces of one direction differ by a few tenths of a degree on clean points and by
    # degrees on scans: group wider than the B-rep's 0.5 degree, well under 45.
    group_angle_deg: float = 5.0
    refine_rounds: int = 2


@dataclass(frozen=True, eq=False)
class Cloud:
    """Points (n, 3) mm with unit PCA normals (n, 3), inlier distance and wide neighbours."""

    points: FloatArray
    normals: FloatArray
    eps: float
    diag: float
    wide: IndexArray  # (n, k) indices of each point's nearest neighbours


@dataclass(frozen=True, eq=False)
class Plane:
    """A fitted plane: unit normal (3,), inliers' mean (3,) mm, inlier indices, hull area mm^2."""

    normal: FloatArray  # (3,) unit
    centre: FloatArray  # (3,) mm, mean of the inliers
    inliers: IndexArray
    area: float


@dataclass(frozen=True, eq=False)
class Cylinder:
    """A fitted cylinder: unit axis (3,), axis point at the inliers' mid-station (3,) mm,
    radius mm, inlier indices, area mm^2 (radius x covered arc x axial length)."""

    direction: FloatArray  # (3,) unit
    point: FloatArray  # (3,) mm, on the axis
    radius: float
    inliers: IndexArray
    area: float


Primitive = Plane | Cylinder


def _local_pca(pts: FloatArray, nbr: IndexArray) -> tuple[FloatArray, FloatArray]:
    """Unit PCA normals (n, 3) of the neighbourhoods ``nbr`` (n, k), and residuals (n,) mm."""
    local = pts[nbr] - pts[nbr].mean(axis=1, keepdims=True)  # (n, k, 3)
    values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local) / nbr.shape[1])
    return vectors[:, :, 0], np.sqrt(np.maximum(values[:, 0], 0.0))


def _inlier_distance(pts: FloatArray, nbr: IndexArray,
                     cfg: PrimitiveConfig) -> tuple[float, FloatArray]:
    """(inlier distance mm, unit normals (n, 3)) from each point's neighbours ``nbr`` (n, k),
    nearest first; see ``PrimitiveConfig.inlier_fraction``."""
    normals = _local_pca(pts, nbr[:, :cfg.neighbours])[0]
    residual = _local_pca(pts, nbr[:, :cfg.noise_neighbours])[1]
    diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    eps = max(cfg.inlier_fraction * diag, cfg.inlier_floor_mm,
              cfg.noise_factor * float(np.median(residual)))
    return eps, normals


def build_cloud(pts: FloatArray, cfg: PrimitiveConfig) -> Cloud:
    """Normals, inlier distance and neighbourhoods of a cloud.

    Args:
        pts: (n, 3) float64 mm, n >= 3, finite, not all on one line.
        cfg: ``neighbours``, ``cylinder_neighbours`` and the inlier distance knobs are used.

    Returns:
        The cloud, ready for ``extract``.
    """
    k = min(max(cfg.cylinder_neighbours, cfg.neighbours, cfg.noise_neighbours), len(pts))
    wide = np.asarray(cKDTree(pts).query(pts, k=k)[1], dtype=np.int64).reshape(len(pts), k)
    eps, normals = _inlier_distance(pts, wide, cfg)
    diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    return Cloud(pts, normals, eps, diag, wide)


# ---------------------------------------------------------------- greedy extraction


def extract(cloud: Cloud, cfg: PrimitiveConfig) -> list[Primitive]:
    """Planes and cylinders found greedily (see the module docstring); seeded by ``cfg.seed``.

    Args:
        cloud: from ``build_cloud``.
        cfg: the fit's knobs.

    Returns:
        Primitives in extraction order, each explaining points no earlier one explained; at
        most ``max_primitives``, each with at least ``min_inliers`` and ``min_inlier_share``.
    """
    pts, rng = cloud.points, np.random.default_rng(cfg.seed)
    need = max(cfg.min_inliers, math.ceil(cfg.min_inlier_share * len(pts)))
    remaining = np.arange(len(pts), dtype=np.int64)
    prims: list[Primitive] = []
    while len(prims) < cfg.max_primitives and len(remaining) >= need:
        found = [c for c in (_best_plane(cloud, remaining, cfg, rng),
                             _best_cylinder(cloud, remaining, cfg, rng))
                 if c is not None and len(c.inliers) >= need]
        if not found:
            break
        best = max(found, key=lambda c: len(c.inliers))  # a plane wins a tie (listed first)
        prims.append(best)
        remaining = np.setdiff1d(remaining, best.inliers)
    log.debug("%d points: %d planes, %d cylinders, %d unexplained, inlier distance %.3g mm",
              len(pts), sum(isinstance(p, Plane) for p in prims),
              sum(isinstance(p, Cylinder) for p in prims), len(remaining), cloud.eps)
    return prims


def _agrees(normals: FloatArray, expected: FloatArray, cfg: PrimitiveConfig) -> npt.NDArray[
        np.bool_]:
    """Unoriented normals within ``normal_angle_deg`` of the expected ones (same shape)."""
    cos = math.cos(math.radians(cfg.normal_angle_deg))
    agree: npt.NDArray[np.bool_] = np.abs(np.sum(normals * expected, axis=-1)) >= cos
    return agree


def _best_plane(cloud: Cloud, remaining: IndexArray, cfg: PrimitiveConfig,
                rng: np.random.Generator) -> Plane | None:
    """The best of ``plane_iterations`` proposals (a point and its normal), refined."""
    seeds = rng.choice(remaining, size=min(cfg.plane_iterations, len(remaining)), replace=False)
    n = cloud.normals[seeds]  # (I, 3)
    pts, nrm = cloud.points[remaining], cloud.normals[remaining]  # (m, 3)
    dist = np.abs(pts @ n.T - np.sum(n * cloud.points[seeds], axis=1))  # (m, I)
    cos = math.cos(math.radians(cfg.normal_angle_deg))
    score = np.count_nonzero((dist <= cloud.eps) & (np.abs(nrm @ n.T) >= cos), axis=0)
    best = int(np.argmax(score))
    return _refine_plane(cloud, remaining, n[best], cloud.points[seeds[best]], cfg)


def _plane_inliers(cloud: Cloud, remaining: IndexArray, normal: FloatArray,
                   centre: FloatArray, cfg: PrimitiveConfig) -> IndexArray:
    pts = cloud.points[remaining]
    near = np.abs((pts - centre) @ normal) <= cloud.eps
    return remaining[near & _agrees(cloud.normals[remaining], normal, cfg)]


def _refine_plane(cloud: Cloud, remaining: IndexArray, normal: FloatArray, centre: FloatArray,
                  cfg: PrimitiveConfig) -> Plane | None:
    """Least-squares plane of the inliers, re-collected ``refine_rounds`` times.

    None when the inliers are too few or form a strip narrower than the inlier distance (a line
    of points lies in every plane through it).
    """
    inliers = _plane_inliers(cloud, remaining, normal, centre, cfg)
    for _ in range(cfg.refine_rounds):
        if len(inliers) < 3:
            return None
        centre = cloud.points[inliers].mean(axis=0)
        normal = np.linalg.svd(cloud.points[inliers] - centre, full_matrices=False)[2][2]
        inliers = _plane_inliers(cloud, remaining, normal, centre, cfg)
    pts = cloud.points[inliers]
    if len(inliers) < 3:
        return None
    spread = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    if spread[1] / math.sqrt(len(pts)) < cloud.eps:  # std across the strip
        return None
    return Plane(normal, pts.mean(axis=0), inliers, _plane_area(pts, normal))


def _plane_area(pts: FloatArray, normal: FloatArray) -> float:
    """Area (mm^2) of the 2D convex hull of points projected on the plane of ``normal``."""
    e1, e2 = perpendicular_pair(normal)
    try:
        return float(ConvexHull(np.column_stack([pts @ e1, pts @ e2])).volume)
    except (QhullError, ValueError):
        return 0.0


def _best_cylinder(cloud: Cloud, remaining: IndexArray, cfg: PrimitiveConfig,
                   rng: np.random.Generator) -> Cylinder | None:
    """The best of ``cylinder_iterations`` proposals (two nearby points and normals), refined."""
    first = rng.choice(remaining, size=cfg.cylinder_iterations, replace=True)
    second = cloud.wide[first, rng.integers(1, cloud.wide.shape[1], size=len(first))]
    axis, centre, radius = _cylinder_proposals(cloud, first, second, cfg)
    if len(axis) == 0:
        return None
    score = np.count_nonzero(_on_cylinders(cloud, remaining, axis, centre, radius, cfg), axis=1)
    best = int(np.argmax(score))
    return _refine_cylinder(cloud, remaining, axis[best], centre[best], float(radius[best]), cfg)


def _cylinder_proposals(cloud: Cloud, first: IndexArray, second: IndexArray,
                        cfg: PrimitiveConfig) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Axes (I, 3) unit, axis points (I, 3) mm and radii (I,) mm from pairs of oriented points.

    The axis is perpendicular to both normals; across it, the two normal lines meet at the
    centre. Pairs with nearly parallel normals, or radii out of range, are dropped.
    """
    ni, nj = cloud.normals[first], cloud.normals[second]
    axis = np.cross(ni, nj)
    turn = np.linalg.norm(axis, axis=1)
    keep = turn >= math.sin(math.radians(cfg.min_normal_turn_deg))
    axis, ni, nj = axis[keep] / turn[keep, None], ni[keep], nj[keep]
    qi, qj = (_across(cloud.points[idx[keep]], axis) for idx in (first, second))
    cos_ij = np.sum(ni * nj, axis=1)
    bi, bj = np.sum((qj - qi) * ni, axis=1), np.sum((qj - qi) * nj, axis=1)
    t = (bi - cos_ij * bj) / (1.0 - cos_ij**2)  # qi + t ni = qj + u nj
    u = cos_ij * t - bj
    radius = 0.5 * (np.abs(t) + np.abs(u))
    ok = (radius > cloud.eps) & (radius <= cfg.max_radius_fraction * cloud.diag)
    return axis[ok], (qi + t[:, None] * ni)[ok], radius[ok]


def _normal_error(normals: FloatArray, expected: FloatArray) -> float:
    """Mean angle (degrees) between unoriented unit normals (m, 3) and the expected ones."""
    cos = np.clip(np.abs(np.sum(normals * expected, axis=-1)), 0.0, 1.0)
    return float(np.degrees(np.median(np.arccos(cos))))


def _radial(pts: FloatArray, axis: FloatArray, centre: FloatArray) -> FloatArray:
    """Unit vectors (m, 3) from the axis line to each point, across the axis."""
    v = pts - centre
    radial = v - np.outer(v @ axis, axis)
    return np.asarray(radial / np.maximum(np.linalg.norm(radial, axis=1), 1e-12)[:, None])


def _across(pts: FloatArray, axis: FloatArray) -> FloatArray:
    """Points (I, 3) with their components along the unit axes (I, 3) removed."""
    return np.asarray(pts - np.sum(pts * axis, axis=1, keepdims=True) * axis)


def _on_cylinders(cloud: Cloud, idx: IndexArray, axis: FloatArray, centre: FloatArray,
                  radius: FloatArray, cfg: PrimitiveConfig) -> npt.NDArray[np.bool_]:
    """(I, m) whether each of the points ``idx`` is an inlier of each of I cylinders."""
    v = cloud.points[idx][None, :, :] - centre[:, None, :]  # (I, m, 3)
    radial = v - np.einsum("imk,ik->im", v, axis)[:, :, None] * axis[:, None, :]
    dist = np.linalg.norm(radial, axis=2)  # (I, m)
    unit = radial / np.maximum(dist, 1e-12)[:, :, None]
    near = np.abs(dist - radius[:, None]) <= cloud.eps
    hit: npt.NDArray[np.bool_] = near & _agrees(cloud.normals[idx][None, :, :], unit, cfg)
    return hit


def _refine_cylinder(cloud: Cloud, remaining: IndexArray, axis: FloatArray,
                     centre: FloatArray, radius: float, cfg: PrimitiveConfig) -> Cylinder | None:
    """Least-squares cylinder of the inliers, re-collected ``refine_rounds`` times.

    None when too few inliers are left, the radius leaves its range, the inliers cover less
    arc than ``min_arc_deg`` or their normals do not follow the surface (a box edge).
    """
    def inliers_of(a: FloatArray, c: FloatArray, r: float) -> IndexArray:
        hit = _on_cylinders(cloud, remaining, a[None], c[None], np.array([r]), cfg)[0]
        return np.asarray(remaining[hit], dtype=np.int64)

    inliers = inliers_of(axis, centre, radius)
    for _ in range(cfg.refine_rounds):
        if len(inliers) < 6:  # five parameters
            return None
        axis, centre, radius = _fit_cylinder(cloud.points[inliers], axis, centre, radius)
        inliers = inliers_of(axis, centre, radius)
    if len(inliers) < 6 or not cloud.eps < radius <= cfg.max_radius_fraction * cloud.diag:
        return None
    arc, length, mid = _extent(cloud.points[inliers], axis, centre, cfg.arc_bins)
    if arc < math.radians(cfg.min_arc_deg):
        return None
    if _normal_error(cloud.normals[inliers], _radial(cloud.points[inliers], axis, centre)) > \
            cfg.max_cylinder_normal_error_deg:
        return None
    return Cylinder(axis, mid, radius, inliers, radius * arc * length)


def _fit_cylinder(pts: FloatArray, axis: FloatArray, centre: FloatArray,
                  radius: float, steps: int = 6) -> tuple[FloatArray, FloatArray, float]:
    """Geometric least squares of distance-to-axis minus radius, by Gauss-Newton steps.

    Each step linearises about the current axis: two tilts of the axis, two shifts of its point
    across it, and the radius (analytic Jacobian; the line's point is kept at the inliers'
    mid-station so that tilting it does not swing the line far from them).

    Returns:
        (unit axis (3,), axis point (3,) mm, radius mm).
    """
    for _ in range(steps):
        centre = centre + float(np.mean((pts - centre) @ axis)) * axis
        e = np.stack(perpendicular_pair(axis))  # (2, 3)
        v = pts - centre
        along = v @ axis
        radial = v - np.outer(along, axis)
        dist = np.linalg.norm(radial, axis=1)
        unit_e = (radial / np.maximum(dist, 1e-12)[:, None]) @ e.T  # (m, 2)
        jac = np.column_stack([-along[:, None] * unit_e, -unit_e, -np.ones(len(pts))])
        step = np.linalg.lstsq(jac, radius - dist, rcond=None)[0]
        axis = axis + step[:2] @ e
        axis = axis / np.linalg.norm(axis)
        centre, radius = centre + step[2:4] @ e, radius + float(step[4])
    return axis, centre, abs(radius)


def _extent(pts: FloatArray, axis: FloatArray, centre: FloatArray,
            bins: int) -> tuple[float, float, FloatArray]:
    """(covered arc rad, axial length mm, axis point (3,) mm at the inliers' mid-station)."""
    e1, e2 = perpendicular_pair(axis)
    v = pts - centre
    along = v @ axis
    angle = np.arctan2(v @ e2, v @ e1)
    covered = np.unique(np.floor((angle + math.pi) / (2 * math.pi) * bins).astype(np.int64) % bins)
    mid = centre + 0.5 * (along.min() + along.max()) * axis
    return 2 * math.pi * len(covered) / bins, float(np.ptp(along)), mid
