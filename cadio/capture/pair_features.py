"""What two parts' points say about their CAD mates: the evidence the relation stage weighs.

The ground truth's symmetric relations are face-level mates of the exact B-rep (DESIGN.md,
"Relations"): ``concentric`` = a coaxial cylinder or cone face of each part within 1 mm of each
other, ``coincident`` = planar faces with opposite normals touching with overlap, ``parallel``
and ``perpendicular`` = the angle between the parts' dominant plane directions. Points carry
none of that directly, and segmenting every face of a 600-point cloud is both slow and blind to
the small faces mates are made of (a washer's bore is 3% of its surface). So the pair is
summarised where mates happen and by what their definitions test:

- the **contact region**: the points of each part within reach of the other. Faces of a mate
  are within 1 mm, so a mate lies in it. A plane fitted to it (residual, how the two parts'
  normals line up with it, its extent) is the evidence of a coincident mate; an axis fitted to
  its normals, and a circle of each part's contact points about that axis (offset of the two
  centres, radii, residual), the evidence of a concentric one;
- each part's **axis** (of its curved points' normals, with a circle about it): two parts
  stacked on one axis are coaxial without any nearby cylinder pair;
- each part's **dominant plane direction**: the normal direction carrying the most planar
  points (points sample area uniformly on CAD surfaces; a scan weighs them as it saw them),
  with its ratio to the runner-up, and the angle between the two parts' directions.

Normals come from local PCA of each cloud. Every feature is symmetric in (a, b), so a pair and
its swap get the same vector. Lengths are millimetres of the parts (the capture's metres over
its scale), angles degrees; a feature that could not be measured takes the value of "far"
(90 degrees, 1000 mm) and its ``*_found`` flag is 0.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from cadio.records import FloatArray

PAIR_FEATURES = (
    "gap_mm", "contact_min", "contact_max",
    "contact_plane_found", "contact_plane_rms_mm", "contact_plane_normal", "contact_extent_mm",
    "contact_axis_found", "contact_axis_flatness", "contact_axis_offset_mm",
    "contact_radius_diff_mm", "contact_circle_rms_mm",
    "axis_found", "axis_angle_deg", "axis_offset_mm",
    "dom_found", "dom_angle_deg", "dom_ratio",
    "spacing_mm",
)
N_PAIR_FEATURES = len(PAIR_FEATURES)
FAR_DEG, FAR_MM = 90.0, 1000.0


@dataclass(frozen=True)
class FeatureConfig:
    """Knobs of the pair evidence. Lengths mm, angles degrees."""

    neighbours: int = 8  # local PCA neighbourhood of a point's normal
    flat: float = 0.02  # a point may seed a plane when its smallest PCA share is under this
    # A plane holds the points within this distance of it (the larger of a floor and a multiple
    # of the points' noise, the median residual of their local PCA) whose normals are within
    # ``plane_normal_deg``: a cylinder's tangent plane holds a strip of width sqrt(8 r eps), a
    # face all its points, so the distance is kept as tight as the noise allows.
    plane_eps_mm: float = 0.02
    noise_factor: float = 4.0
    plane_normal_deg: float = 30.0
    min_plane: int = 8  # points of the smallest plane kept
    max_planes: int = 12
    max_seeds: int = 200  # flat points proposing planes
    # A point is in the contact region when the other part is within this many point spacings
    # plus the mate's 1 mm (the faces of a concentric mate are within 1 mm).
    contact_spacings: float = 2.0
    contact_mm: float = 1.0
    min_contact: int = 6  # points of each part the contact fits need
    group_deg: float = 5.0  # plane directions within this angle are one direction
    dominant_cap: float = 10.0  # a part with a single plane direction has this ratio


@dataclass(frozen=True, eq=False)
class PartCloud:
    """A part's points (n, 3) mm with unit normals (n, 3), which points lie on a fitted plane
    (n,) bool, the planes (unit normal, inlier count) and the median spacing (mm)."""

    points: FloatArray
    normals: FloatArray
    planar: npt.NDArray[np.bool_]
    planes: tuple[tuple[FloatArray, int], ...]
    spacing: float


def part_cloud(points_mm: FloatArray, cfg: FeatureConfig = FeatureConfig()) -> PartCloud:
    """Normals, planes and spacing of one part's points (mm); non-finite points dropped."""
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < 4:
        return PartCloud(pts, np.zeros_like(pts), np.zeros(len(pts), dtype=bool), (), 0.0)
    k = min(cfg.neighbours, len(pts))
    dist, nbr = cKDTree(pts).query(pts, k=k)
    local = pts[nbr] - pts[nbr].mean(axis=1, keepdims=True)  # (n, k, 3)
    evals, evecs = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    share = evals[:, 0] / np.maximum(evals.sum(axis=1), 1e-30)
    normals = evecs[:, :, 0]
    spacing = float(np.median(dist[:, 1])) if k > 1 else 0.0
    noise = float(np.median(np.sqrt(np.clip(evals[:, 0], 0.0, None) / k)))
    eps = max(cfg.plane_eps_mm, cfg.noise_factor * noise)
    planar, planes = _extract_planes(pts, normals, share < cfg.flat, eps, cfg)
    return PartCloud(pts, normals, planar, planes, spacing)


def _extract_planes(pts: FloatArray, normals: FloatArray, flat: npt.NDArray[np.bool_],
                    eps: float, cfg: FeatureConfig
                    ) -> tuple[npt.NDArray[np.bool_], tuple[tuple[FloatArray, int], ...]]:
    """Planes taken greedily: every flat point proposes the plane through it along its normal;
    the proposal holding the most unclaimed points wins and claims them, unless its points bend
    away from it across their narrow side (a strip of a cylinder, which a tangent plane holds
    within ``eps``): then that proposal is dropped."""
    cos = math.cos(math.radians(cfg.plane_normal_deg))
    seeds = np.flatnonzero(flat)
    if len(seeds) == 0:
        return np.zeros(len(pts), dtype=bool), ()
    if len(seeds) > cfg.max_seeds:  # evenly spread proposals: a face gives many alike
        seeds = seeds[np.linspace(0, len(seeds) - 1, cfg.max_seeds).astype(np.int64)]
    # distance of every point from the plane through each seed along its normal: (S, n)
    offsets = np.abs(pts @ normals[seeds].T - np.einsum("sj,sj->s", normals[seeds], pts[seeds])).T
    holds = (offsets <= eps) & (np.abs(normals[seeds] @ normals.T) >= cos)  # (S, n)
    free = np.ones(len(pts), dtype=bool)
    counts = holds.sum(axis=1)  # points each proposal holds among the unclaimed ones
    planes: list[tuple[FloatArray, int]] = []
    for _ in range(4 * cfg.max_planes):
        best = int(np.argmax(counts))
        if counts[best] < cfg.min_plane or len(planes) == cfg.max_planes:
            break
        members = holds[best] & free
        normal = normals[seeds[best]]
        if _bends(pts[members], normal, eps):
            counts[members[seeds]] = 0  # no seed on that strip proposes its plane again
            counts[best] = 0
            continue
        planes.append((normal, int(counts[best])))
        free &= ~members
        counts -= holds[:, members].sum(axis=1)
    return ~free, tuple(planes)


def _bends(points: FloatArray, normal: FloatArray, eps: float) -> bool:
    """Whether points held by a plane curve away from it across their narrow side: the
    parabola of their offsets over the narrow coordinate (beside a tilt) sags by more than half
    ``eps`` and explains most of their spread (a cylinder's strip; a face's offsets are flat
    noise)."""
    centred = points - points.mean(axis=0)
    d = centred @ normal
    inplane = centred - np.outer(d, normal)
    _, _, vt = np.linalg.svd(inplane, full_matrices=False)
    u, w = inplane @ vt[1], inplane @ vt[0]  # the narrow and the long in-plane directions
    # a linear term in each direction takes up the tilt of the proposal's normal
    design = np.column_stack([u**2, u, w, np.ones_like(u)])
    coef, *_ = np.linalg.lstsq(design, d, rcond=None)
    half = (u.max() - u.min()) / 2
    sag = abs(float(coef[0])) * half**2
    spread = float(np.var(d))
    explained = 1.0 - float(np.var(d - design @ coef)) / spread if spread > 0 else 0.0
    return sag > 0.5 * eps and explained > 0.5


def pair_features(a: PartCloud, b: PartCloud,
                  cfg: FeatureConfig = FeatureConfig()) -> npt.NDArray[np.float32]:
    """(``N_PAIR_FEATURES``,) the pair's evidence, in ``PAIR_FEATURES`` order."""
    if len(a.points) == 0 or len(b.points) == 0:
        out = np.array([FAR_MM, 0, 0, 0, FAR_MM, 0, 0, 0, 0, FAR_MM, FAR_MM, FAR_MM,
                        0, FAR_DEG, FAR_MM, 0, FAR_DEG, 0, 0], dtype=np.float32)
        return out
    da = cKDTree(b.points).query(a.points, k=1)[0]
    db = cKDTree(a.points).query(b.points, k=1)[0]
    reach = cfg.contact_mm + cfg.contact_spacings * max(a.spacing, b.spacing)
    in_a, in_b = da <= reach, db <= reach
    shares = sorted((float(in_a.mean()), float(in_b.mean())))
    feats = [float(min(da.min(), db.min())), *shares]
    feats += _contact_plane(a, b, in_a, in_b, cfg)
    feats += _contact_axis(a, b, in_a, in_b, cfg)
    feats += _part_axes(a, b, cfg)
    feats += _dominant_pair(a, b, cfg)
    feats.append(max(a.spacing, b.spacing))
    return np.array(feats, dtype=np.float32)


def _contact_plane(a: PartCloud, b: PartCloud, in_a: npt.NDArray[np.bool_],
                   in_b: npt.NDArray[np.bool_], cfg: FeatureConfig) -> list[float]:
    """(found, rms residual, normal agreement, in-plane extent) of a plane through the planar
    points of the contact region (faces of a coincident mate are planes; edges near the other
    part are not): agreement is the smaller of the two parts' median |n . plane normal|, 1 when
    both touch it face-on."""
    flat_a, flat_b = in_a & a.planar, in_b & b.planar
    if flat_a.sum() < cfg.min_contact or flat_b.sum() < cfg.min_contact:
        return [0.0, FAR_MM, 0.0, 0.0]
    pts = np.concatenate([a.points[flat_a], b.points[flat_b]])
    centred = pts - pts.mean(axis=0)
    _, sing, vt = np.linalg.svd(centred, full_matrices=False)
    normal = vt[2]
    rms = float(sing[2] / math.sqrt(len(pts)))
    agree = min(float(np.median(np.abs(a.normals[flat_a] @ normal))),
                float(np.median(np.abs(b.normals[flat_b] @ normal))))
    return [1.0, rms, agree, float(sing[1] / math.sqrt(len(pts)))]


def _axis_of(normals: FloatArray) -> tuple[FloatArray, float]:
    """The direction most perpendicular to the normals, and its flatness: the smallest over
    the middle eigenvalue of the normals' second moment (0 for a perfect cylinder, where every
    normal is perpendicular to the axis; about 1 when the normals spread every way)."""
    evals, evecs = np.linalg.eigh(normals.T @ normals / max(len(normals), 1))
    return evecs[:, 0], float(evals[0] / max(evals[1], 1e-12))


def _circle(points: FloatArray, axis: FloatArray) -> tuple[FloatArray, float, float]:
    """Centre (3,) on the plane through the points' mean, radius and rms residual of a circle
    fitted (Kasa's algebraic fit) to the points projected along ``axis``."""
    basis = np.linalg.svd(np.eye(3) - np.outer(axis, axis))[0][:, :2]
    origin = points.mean(axis=0)
    uv = (points - origin) @ basis
    design = np.column_stack([uv, np.ones(len(uv))])
    rhs = (uv**2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(design, rhs, rcond=None)
    centre2 = sol[:2] / 2
    radius = math.sqrt(max(float(sol[2] + centre2 @ centre2), 0.0))
    resid = np.linalg.norm(uv - centre2, axis=1) - radius
    return origin + basis @ centre2, radius, float(np.sqrt(np.mean(resid**2)))


def _offset(p: FloatArray, q: FloatArray, axis: FloatArray) -> float:
    """Distance between two points measured across ``axis``."""
    d = q - p
    return float(np.linalg.norm(d - np.dot(d, axis) * axis))


def _contact_axis(a: PartCloud, b: PartCloud, in_a: npt.NDArray[np.bool_],
                  in_b: npt.NDArray[np.bool_], cfg: FeatureConfig) -> list[float]:
    """(found, flatness, offset of the circle centres, radius difference, worse circle rms) of
    the contact region's curved points about the axis their normals share. The axis is taken
    from the part whose curved contact points agree best on one (a shaft's many points rather
    than the few of the bore around it), and each part's points get a circle about it."""
    curved_a, curved_b = in_a & ~a.planar, in_b & ~b.planar
    if curved_a.sum() < cfg.min_contact or curved_b.sum() < cfg.min_contact:
        return [0.0, 0.0, FAR_MM, FAR_MM, FAR_MM]
    axis, flat = min((_axis_of(a.normals[curved_a]), _axis_of(b.normals[curved_b])),
                     key=lambda fit: fit[1])
    ca, ra, ea = _circle(a.points[curved_a], axis)
    cb, rb, eb = _circle(b.points[curved_b], axis)
    return [1.0, flat, _offset(ca, cb, axis), abs(ra - rb), max(ea, eb)]


def _part_axes(a: PartCloud, b: PartCloud, cfg: FeatureConfig) -> list[float]:
    """(found, angle between the parts' axes, offset of their circle centres across them)."""
    axes = []
    for part in (a, b):
        curved = ~part.planar
        if curved.sum() < cfg.min_contact:
            return [0.0, FAR_DEG, FAR_MM]
        axis, _ = _axis_of(part.normals[curved])
        centre, _, _ = _circle(part.points[curved], axis)
        axes.append((axis, centre))
    (ua, pa), (ub, pb) = axes
    angle = math.degrees(math.acos(min(1.0, abs(float(ua @ ub)))))
    mean = ua if ua @ ub >= 0 else -ua
    mean = (mean + ub) / np.linalg.norm(mean + ub)
    return [1.0, angle, _offset(pa, pb, mean)]


def dominant_direction(part: PartCloud,
                       cfg: FeatureConfig = FeatureConfig()) -> tuple[FloatArray | None, float]:
    """The plane direction carrying the most points of fitted planes (points sample area),
    and its ratio to the runner-up's (``cfg.dominant_cap`` with one direction only); (None, 0)
    without planes."""
    groups: list[tuple[FloatArray, int]] = []
    cos = math.cos(math.radians(cfg.group_deg))
    for normal, count in part.planes:
        for i, (direction, total) in enumerate(groups):
            if abs(float(direction @ normal)) >= cos:
                groups[i] = (direction, total + count)
                break
        else:
            groups.append((normal, count))
    if not groups:
        return None, 0.0
    groups.sort(key=lambda g: -g[1])
    ratio = cfg.dominant_cap if len(groups) == 1 else min(cfg.dominant_cap,
                                                          groups[0][1] / groups[1][1])
    return groups[0][0], float(ratio)


def _dominant_pair(a: PartCloud, b: PartCloud, cfg: FeatureConfig) -> list[float]:
    """(found, angle between the dominant directions in [0, 90], the smaller ratio)."""
    da, ra = dominant_direction(a, cfg)
    db, rb = dominant_direction(b, cfg)
    if da is None or db is None:
        return [0.0, FAR_DEG, 0.0]
    return [1.0, math.degrees(math.acos(min(1.0, abs(float(da @ db))))), min(ra, rb)]


# How each feature enters a network: lengths as log1p(mm) (a tenth of a millimetre and a metre
# both stay in range), angles over 90 degrees, flags, shares and ratios as they are (ratios over
# their cap).
_LENGTH = {i for i, n in enumerate(PAIR_FEATURES) if n.endswith("_mm")}
_ANGLE = {i for i, n in enumerate(PAIR_FEATURES) if n.endswith("_deg")}
_RATIO = {PAIR_FEATURES.index("dom_ratio")}


def encode_features(features: npt.NDArray[np.floating],
                    cfg: FeatureConfig = FeatureConfig()) -> npt.NDArray[np.float32]:
    """(N, ``N_PAIR_FEATURES``) features scaled for a network (see the scales above)."""
    x = np.asarray(features, dtype=np.float64).copy()
    for i in range(x.shape[-1]):
        if i in _LENGTH:
            x[..., i] = np.log1p(np.clip(x[..., i], 0.0, None))
        elif i in _ANGLE:
            x[..., i] = x[..., i] / 90.0
        elif i in _RATIO:
            x[..., i] = x[..., i] / cfg.dominant_cap
    return x.astype(np.float32)


def pair_features_many(points: npt.NDArray[np.floating] | Sequence[Sequence[npt.NDArray[Any]]],
                       mm_per_unit: npt.ArrayLike,
                       keys: Sequence[tuple[Hashable, Hashable]] | None = None,
                       cloud: Callable[[FloatArray], PartCloud] = part_cloud
                       ) -> npt.NDArray[np.float32]:
    """(N, ``N_PAIR_FEATURES``) features of pairs (N, 2, k, 3) in any unit, or of N pairs of
    clouds of any sizes (k_a, 3), (k_b, 3). Every feature is invariant under a rigid motion of
    the pair: the clouds may be in any frame.

    Args:
        mm_per_unit: (N,) millimetres of the parts per unit of ``points``.
        keys: per row, a key of each part's cloud: a cloud met again (a part of an assembly in
            many pairs) gets its normals once.
    """
    mm = np.broadcast_to(np.asarray(mm_per_unit, dtype=np.float64), (len(points),))
    cache: dict[Hashable, PartCloud] = {}

    def part(i: int, k: int) -> PartCloud:
        key = (i, k) if keys is None else keys[i][k]
        if key not in cache:
            cache[key] = cloud(np.asarray(points[i][k], dtype=np.float64) * mm[i])
        return cache[key]

    out = np.zeros((len(points), N_PAIR_FEATURES), dtype=np.float32)
    for i in range(len(points)):
        out[i] = pair_features(part(i, 0), part(i, 1))
    return out
