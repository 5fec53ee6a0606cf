"""The ``geometric`` relation baseline: planes and cylinders fitted to points, then ``relate``.

The ground truth decides the ten relations on features of the exact B-rep
(``cadio.cad.features``). This baseline builds the same ``Features`` record from a part's points
alone and hands it to the same ``cadio.truth.relations.relate``, so any difference between the
two comes from the features, never from a second definition of the relations.

Primitives come from ``cadio.capture.ransac`` (efficient RANSAC of planes and cylinders on
points with local PCA normals). Here they are grouped as the B-rep features group faces (planes
by normal direction, cylinders by axis line), and the principal plane and axis follow the same
largest-area rule and tie flag. Areas are measured on the inliers (a plane's 2D hull, a
cylinder's covered arc times its length) rather than counted in points: a single-view scan
samples surfaces facing the camera more densely than grazing ones, and the area of a face does
not depend on that. The centroid is the volume centroid of the points' convex hull: the B-rep
truth's volume centroid for a convex part, and, unlike the mean of the points, independent of
how densely each region is sampled (the mean of 600 random surface samples of a 40 mm plate
wanders by about a millimetre, enough to tip a stacked pair out of its 15 degree cone). A
partial scan's hull is the seen side's, so its centroid leans towards the camera.

The relation tolerances stay those of the truth; on fitted points they are strict, so the
baseline is honestly weak on ``coincident`` and ``concentric``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import numpy.typing as npt
from scipy.spatial import ConvexHull, QhullError

from cadio.capture.ransac import (
    Cylinder,
    Plane,
    Primitive,
    PrimitiveConfig,
    build_cloud,
    extract,
)
from cadio.records import (
    AxisGroup,
    Features,
    FloatArray,
    PlaneGroup,
    canonical_direction,
    dominant_choice,
    principal_choice,
)
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.relations import RELATIONS, RelationResult, Vector3, relate

__all__ = [
    "DEFAULT_PRIMITIVES", "PrimitiveConfig", "fit_features", "relate_many",
    "relate_points",
]

DEFAULT_PRIMITIVES = PrimitiveConfig()


def fit_features(points_mm: FloatArray, cfg: PrimitiveConfig = DEFAULT_PRIMITIVES) -> Features:
    """Features of one part from its points: planes and cylinders fitted by RANSAC.

    Args:
        points_mm: (n, 3) float64, mm, in the frame the relations are asked in; surface samples,
            a partial scan or voxel centres.
        cfg: the fit's knobs; the same seed gives the same features.

    Returns:
        Features: centroid, area and volume of the points' convex hull (the mean of the
        points and zeros for a flat or linear cloud), bbox of the points, plane groups and
        cylinder axis groups (face ids are primitive numbers in extraction order), principal
        plane and axis by largest area with tie flags. A degenerate cloud (collinear,
        coincident) has none.

    Raises:
        ValueError: not an (n, 3) array, non-finite values, or fewer than 3 points.
    """
    pts = _checked(points_mm)
    area, volume, centroid = _hull_measures(pts)
    cloud = build_cloud(pts, cfg) if _spans_plane(pts) else None
    numbered = list(enumerate(extract(cloud, cfg))) if cloud is not None else []
    planes = _group_planes([(i, p) for i, p in numbered if isinstance(p, Plane)], centroid, cfg)
    axes = _group_axes([(i, p) for i, p in numbered if isinstance(p, Cylinder)],
                       0.0 if cloud is None else cloud.eps, cfg)
    plane_pick, plane_tie = principal_choice([g.area for g in planes])
    axis_pick, axis_tie = principal_choice([a.area for a in axes])
    if axis_pick is not None:
        axes = (axes[axis_pick], *(a for i, a in enumerate(axes) if i != axis_pick))
    dominant, runner_up = dominant_choice(planes, DEFAULT_TOLERANCES.dominant_group_deg,
                                          DEFAULT_TOLERANCES.dominant_area_ratio)
    return Features(
        centroid=centroid, bbox_min=pts.min(axis=0), bbox_max=pts.max(axis=0),
        volume=volume, area=area, planes=planes, axes=axes,
        principal_plane=None if plane_pick is None else planes[plane_pick].normal,
        principal_axis=axes[0] if axis_pick is not None else None,
        principal_plane_tie=plane_tie, principal_axis_tie=axis_tie, n_faces=len(numbered),
        dominant_plane=dominant, dominant_runner_up=runner_up,
    )


def relate_points(
    points_a_mm: FloatArray,
    points_b_mm: FloatArray,
    view_axis: Vector3,
    tol: Tolerances = DEFAULT_TOLERANCES,
    cfg: PrimitiveConfig = DEFAULT_PRIMITIVES,
) -> RelationResult:
    """The ten relations of the ordered pair (a, b) from their points (the geometric baseline).

    Args:
        points_a_mm, points_b_mm: (n, 3) float64, mm, both in one world frame (Z up).
        view_axis: (3,) the observer's forward direction.
        tol: the relations' tolerances (those of the ground truth).
        cfg: the primitive fit's knobs.

    Returns:
        ``relate(fit_features(a), fit_features(b), view_axis, tol)``.

    Raises:
        ValueError: a cloud ``fit_features`` refuses, or a view axis ``relate`` refuses.
    """
    return relate(fit_features(points_a_mm, cfg), fit_features(points_b_mm, cfg), view_axis, tol)


def relate_many(
    clouds: Sequence[FloatArray],
    pairs: npt.ArrayLike,
    view_axes: npt.ArrayLike,
    tol: Tolerances = DEFAULT_TOLERANCES,
    cfg: PrimitiveConfig = DEFAULT_PRIMITIVES,
) -> npt.NDArray[np.bool_]:
    """Relations of many ordered pairs; each cloud is fitted once however many pairs use it.

    Args:
        clouds: k point clouds, each (n_i, 3) float64 mm in one world frame.
        pairs: (m, 2) int, indices into ``clouds`` of (a, b).
        view_axes: (3,) for every pair, or (m, 3), one per pair.
        tol, cfg: as ``relate_points``.

    Returns:
        (m, 10) bool, columns in ``Relation`` order.

    Raises:
        ValueError: pairs or view axes of the wrong shape, an index out of range, or a cloud
            ``fit_features`` refuses (only clouds used by some pair are fitted).
    """
    idx = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    views = np.broadcast_to(np.asarray(view_axes, dtype=np.float64), (len(idx), 3))
    if len(idx) and (idx.min() < 0 or idx.max() >= len(clouds)):
        raise ValueError(f"pair indices must lie in [0, {len(clouds)}), got {idx.min()}.."
                         f"{idx.max()}")
    feats = {int(i): fit_features(clouds[int(i)], cfg) for i in np.unique(idx)}
    out = np.zeros((len(idx), len(RELATIONS)), dtype=bool)
    for row, ((a, b), view) in enumerate(zip(idx, views, strict=True)):
        out[row] = relate(feats[int(a)], feats[int(b)], view, tol).truth
    return out


# ---------------------------------------------------------------- the cloud


def _checked(points_mm: FloatArray) -> FloatArray:
    pts = np.asarray(points_mm, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be an (n, 3) array, got shape {pts.shape}")
    if len(pts) < 3:
        raise ValueError(f"need at least 3 points to fit primitives, got {len(pts)}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points contain NaN or infinite coordinates")
    return pts


def _spans_plane(pts: FloatArray) -> bool:
    """Whether the points span at least two dimensions (not all on one line or one point)."""
    s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    return bool(s[0] > 0.0 and s[1] > 1e-9 * s[0])


def _hull_measures(pts: FloatArray) -> tuple[float, float, FloatArray]:
    """(area mm^2, volume mm^3, volume centroid (3,) mm) of the convex hull.

    A flat or linear cloud has no hull: (0, 0, the mean of the points).
    """
    try:
        hull = ConvexHull(pts)
    except (QhullError, ValueError):
        return 0.0, 0.0, pts.mean(axis=0)
    apex = pts[hull.vertices].mean(axis=0)  # inside the hull: cones to it tile the volume
    tri = pts[hull.simplices]  # (f, 3, 3)
    vols = np.abs(np.einsum("fi,fi->f", tri[:, 0] - apex,
                            np.cross(tri[:, 1] - apex, tri[:, 2] - apex))) / 6.0
    centres = (tri.sum(axis=1) + apex) / 4.0
    centroid = vols @ centres / vols.sum() if vols.sum() > 0 else pts.mean(axis=0)
    return float(hull.area), float(hull.volume), np.asarray(centroid, dtype=np.float64)


# ---------------------------------------------------------------- grouping, as the B-rep's


def _cluster(items: Sequence[tuple[int, Primitive]],
             same: Callable[[Primitive, Primitive], bool]) -> list[list[tuple[int, Primitive]]]:
    """Greedy clustering in extraction order: an item joins the first cluster whose seed fits."""
    clusters: list[list[tuple[int, Primitive]]] = []
    for item in items:
        home = next((c for c in clusters if same(c[0][1], item[1])), None)
        if home is None:
            clusters.append([item])
        else:
            home.append(item)
    return clusters


def _mean_direction(directions: Sequence[FloatArray], weights: Sequence[float]) -> FloatArray:
    """Weighted mean of unit directions, signs aligned to the first, canonical sign."""
    w = np.asarray(weights, dtype=np.float64)
    w = w if w.sum() > 0 else np.ones_like(w)
    total = sum(wi * (1.0 if d @ directions[0] >= 0 else -1.0) * d
                for wi, d in zip(w, directions, strict=True))
    return canonical_direction(total)


def _parallel(a: FloatArray, b: FloatArray, angle_deg: float) -> bool:
    return abs(float(a @ b)) >= math.cos(math.radians(angle_deg))


def _group_planes(items: Sequence[tuple[int, Plane]], centroid: FloatArray,
                  cfg: PrimitiveConfig) -> tuple[PlaneGroup, ...]:
    """Plane groups by normal direction; outward = the normal points away from the centroid."""
    def same(a: Primitive, b: Primitive) -> bool:
        assert isinstance(a, Plane) and isinstance(b, Plane)
        return _parallel(a.normal, b.normal, cfg.group_angle_deg)

    groups = []
    for members in _cluster(items, same):
        planes = [p for _, p in members if isinstance(p, Plane)]
        normal = _mean_direction([p.normal for p in planes], [p.area for p in planes])
        groups.append(PlaneGroup(
            normal=normal, area=float(sum(p.area for p in planes)),
            face_ids=tuple(i for i, _ in members), face_areas=tuple(p.area for p in planes),
            offsets=tuple(float(normal @ p.centre) for p in planes),
            outward=tuple(1 if normal @ (p.centre - centroid) > 0 else -1 for p in planes),
        ))
    return tuple(groups)


def _line_gap(a: Cylinder, b: Cylinder) -> float:
    """Largest distance of either axis point from the other axis line, mm."""
    def off(p: FloatArray, q: FloatArray, d: FloatArray) -> float:
        r = p - q
        return float(np.linalg.norm(r - (r @ d) * d))

    return max(off(a.point, b.point, b.direction), off(b.point, a.point, a.direction))


def _group_axes(items: Sequence[tuple[int, Cylinder]], eps: float,
                cfg: PrimitiveConfig) -> tuple[AxisGroup, ...]:
    """Cylinder groups sharing an axis line: within ``group_angle_deg`` and the inlier distance
    (axis lines closer than the points' own scatter cannot be told apart)."""
    def same(a: Primitive, b: Primitive) -> bool:
        assert isinstance(a, Cylinder) and isinstance(b, Cylinder)
        return _parallel(a.direction, b.direction, cfg.group_angle_deg) and _line_gap(a, b) <= eps

    groups = []
    for members in _cluster(items, same):
        cyls = [c for _, c in members if isinstance(c, Cylinder)]
        direction = _mean_direction([c.direction for c in cyls], [c.area for c in cyls])
        point = np.mean([c.point for c in cyls], axis=0)
        groups.append(AxisGroup(
            kind="cylinder", direction=direction, point=point - (point @ direction) * direction,
            area=float(sum(c.area for c in cyls)), face_ids=tuple(i for i, _ in members),
            radii=tuple(c.radius for c in cyls),
        ))
    return tuple(groups)
