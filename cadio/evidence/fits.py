"""What a part's points are made of: normals, planes, cylinders and the dominant plane
direction, fitted to one cloud (the pair evidence of ``cadio.evidence.pair_features`` compares
two). Lengths are millimetres, angles degrees; normals come from local PCA and carry no sign,
unless the cloud brings exact ones (the CAD's samples of the ``truth`` input).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from cadio.records import FloatArray


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
    exact_normal_deg: float = 0.1  # the same, where the normals are exact (CAD samples)
    # ...and the distance, there: CAD samples lie on their faces. The noise of a local PCA
    # (neighbourhoods across edges) merged faces millimetres apart into one plane: a caster's
    # plate held its faces 111.0 to 113.5 mm along its normal, and the face pair of its mate
    # read 1.16 mm apart, not the CAD's 0.
    exact_plane_mm: float = 0.02
    min_plane: int = 8  # points of the smallest plane kept
    max_planes: int = 12
    # Where the normals are exact a plane costs little and never a strip of a cylinder: every
    # face of a runner-up direction counts towards the dominant direction's ratio.
    exact_max_planes: int = 48
    max_seeds: int = 200  # flat points proposing planes
    # A point is in the contact region when the other part is within this many point spacings
    # plus the mate's 1 mm (the faces of a concentric mate are within 1 mm).
    contact_spacings: float = 2.0
    contact_mm: float = 1.0
    min_contact: int = 6  # points of each part the contact fits need
    # Cylinders of a part's curved contact points: hypotheses drawn from pairs of its points
    # (their normals' cross product is the axis, their normal lines meet on it), at most
    # ``max_cylinders`` taken greedily by support; a point is on one when its distance from the
    # axis is within the larger of ``plane_eps_mm`` and half a spacing of the radius and its
    # normal within ``cylinder_normal_deg`` of perpendicular to the axis.
    cylinder_hypotheses: int = 64
    max_cylinders: int = 3
    refine_cylinders: bool = True  # off: the axis the members' normals give (as before)
    cylinder_normal_deg: float = 15.0
    group_deg: float = 5.0  # plane directions within this angle are one direction
    dominant_cap: float = 10.0  # a part with a single plane direction has this ratio


DEFAULT_FEATURES = FeatureConfig()


@dataclass(frozen=True, eq=False)
class PartCloud:
    """A part's points (n, 3) mm with unit normals (n, 3), which points lie on a fitted plane
    (n,) bool, the planes (unit normal, inlier count), the median spacing (mm) and each point's
    plane (n,) int, an index into ``planes`` or -1. exact: the normals were given (the CAD's
    faces under its samples), so each plane is one face's plane."""

    points: FloatArray
    normals: FloatArray
    planar: npt.NDArray[np.bool_]
    planes: tuple[tuple[FloatArray, int], ...]
    spacing: float
    plane_of: npt.NDArray[np.int64] | None = None
    exact: bool = False

    @cached_property
    def tree(self) -> cKDTree:
        """The k-d tree of the points, built once (a part meets many others in a view)."""
        return cKDTree(self.points)

    def plane_members(self) -> list[npt.NDArray[np.int64]]:
        """The point indices of each plane, in ``planes`` order."""
        if self.plane_of is None:
            return [np.zeros(0, dtype=np.int64) for _ in self.planes]
        return [np.flatnonzero(self.plane_of == i) for i in range(len(self.planes))]


def part_cloud(points_mm: FloatArray, cfg: FeatureConfig = DEFAULT_FEATURES,
               normals: FloatArray | None = None) -> PartCloud:
    """Normals, planes and spacing of one part's points (mm); non-finite points dropped.

    ``normals``: (n, 3) unit normals known exactly (the faces of the CAD under its samples,
    ``cadio.evidence.cad_samples``), taken instead of local PCA's. A plane then holds only
    points whose normals lie within ``exact_normal_deg`` of its own: a face's normals are one,
    a cylinder's turn, so no strip of a cylinder passes for a plane however flat its facets,
    and a narrow face (a washer's rim) is found wherever its points are, flat neighbourhood or
    not."""
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    keep = np.all(np.isfinite(pts), axis=1)
    given = None if normals is None else np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if given is not None:
        if len(given) != len(pts):
            raise ValueError(f"{len(given)} normals for {len(pts)} points")
        keep &= np.all(np.isfinite(given), axis=1)
        given = given[keep]
    pts = pts[keep]
    if len(pts) < 4:
        return PartCloud(pts, np.zeros_like(pts), np.zeros(len(pts), dtype=bool), (), 0.0,
                         np.full(len(pts), -1, dtype=np.int64))
    k = min(cfg.neighbours, len(pts))
    dist, nbr = cKDTree(pts).query(pts, k=k)
    local = pts[nbr] - pts[nbr].mean(axis=1, keepdims=True)  # (n, k, 3)
    evals, evecs = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    share = evals[:, 0] / np.maximum(evals.sum(axis=1), 1e-30)
    spacing = float(np.median(dist[:, 1])) if k > 1 else 0.0
    noise = float(np.median(np.sqrt(np.clip(evals[:, 0], 0.0, None) / k)))
    eps = max(cfg.plane_eps_mm, cfg.noise_factor * noise)
    if given is None:
        plane_of, planes = _extract_planes(pts, evecs[:, :, 0], share < cfg.flat, eps, cfg,
                                           cfg.plane_normal_deg, cfg.max_planes)
        return PartCloud(pts, evecs[:, :, 0], plane_of >= 0, planes, spacing, plane_of)
    eps = cfg.exact_plane_mm
    plane_of, planes = _extract_planes(pts, given, _shared_normals(pts, given, eps, cfg), eps,
                                       cfg, cfg.exact_normal_deg, cfg.exact_max_planes)
    return PartCloud(pts, given, plane_of >= 0, planes, spacing, plane_of, exact=True)


def _shared_normals(pts: FloatArray, normals: FloatArray, eps: float, cfg: FeatureConfig
                    ) -> npt.NDArray[np.bool_]:
    """(n,) one point of each exact normal direction (sign ignored) and offset (in steps of
    ``eps``) that at least ``min_plane`` points share: the seeds of planes where the normals
    are exact."""
    canonical = normals * np.where(normals[:, [0]] < 0, -1.0, 1.0)
    offset = np.einsum("ij,ij->i", canonical, pts) / max(eps, 1e-9)
    key = np.column_stack([np.round(canonical, 4), np.round(offset)])
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    seeds = np.zeros(len(normals), dtype=bool)
    seeds[first[counts >= cfg.min_plane]] = True
    return seeds


def _extract_planes(pts: FloatArray, normals: FloatArray, flat: npt.NDArray[np.bool_],
                    eps: float, cfg: FeatureConfig, normal_deg: float, most: int
                    ) -> tuple[npt.NDArray[np.int64], tuple[tuple[FloatArray, int], ...]]:
    """Planes taken greedily: every flat point proposes the plane through it along its normal;
    the proposal holding the most unclaimed points wins and claims them, unless its points bend
    away from it across their narrow side (a strip of a cylinder, which a tangent plane holds
    within ``eps``): then that proposal is dropped. Returns each point's plane (-1: none) and
    the planes, at most ``most``. A plane holds points whose normals lie within ``normal_deg``
    of its own."""
    cos = math.cos(math.radians(normal_deg))
    seeds = np.flatnonzero(flat)
    plane_of = np.full(len(pts), -1, dtype=np.int64)
    if len(seeds) == 0:
        return plane_of, ()
    if len(seeds) > cfg.max_seeds:  # evenly spread proposals: a face gives many alike
        seeds = seeds[np.linspace(0, len(seeds) - 1, cfg.max_seeds).astype(np.int64)]
    # distance of every point from the plane through each seed along its normal: (S, n)
    offsets = np.abs(pts @ normals[seeds].T - np.einsum("sj,sj->s", normals[seeds], pts[seeds])).T
    holds = (offsets <= eps) & (np.abs(normals[seeds] @ normals.T) >= cos)  # (S, n)
    free = np.ones(len(pts), dtype=bool)
    counts = holds.sum(axis=1)  # points each proposal holds among the unclaimed ones
    planes: list[tuple[FloatArray, int]] = []
    for _ in range(4 * most):
        best = int(np.argmax(counts))
        if counts[best] < cfg.min_plane or len(planes) == most:
            break
        members = holds[best] & free
        normal = normals[seeds[best]]
        if _bends(pts[members], normal, eps):
            counts[members[seeds]] = 0  # no seed on that strip proposes its plane again
            counts[best] = 0
            continue
        plane_of[members] = len(planes)
        planes.append((normal, int(counts[best])))
        free &= ~members
        counts -= holds[:, members].sum(axis=1)
    return plane_of, tuple(planes)


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


def axis_of(normals: FloatArray) -> tuple[FloatArray, float]:
    """The direction most perpendicular to the normals, and its flatness: the smallest over
    the middle eigenvalue of the normals' second moment (0 for a perfect cylinder, where every
    normal is perpendicular to the axis; about 1 when the normals spread every way)."""
    evals, evecs = np.linalg.eigh(normals.T @ normals / max(len(normals), 1))
    return evecs[:, 0], float(evals[0] / max(evals[1], 1e-12))


def across(axis: FloatArray) -> FloatArray:
    """(3, 2) two orthonormal directions spanning the plane across a unit ``axis``."""
    basis: FloatArray = np.linalg.svd(np.eye(3) - np.outer(axis, axis))[0][:, :2]
    return basis


def circle(points: FloatArray, axis: FloatArray) -> tuple[FloatArray, float, float]:
    """Centre (3,) on the plane through the points' mean, radius and rms residual of a circle
    fitted (Kasa's algebraic fit) to the points projected along ``axis``."""
    basis = across(axis)
    origin = points.mean(axis=0)
    uv = (points - origin) @ basis
    design = np.column_stack([uv, np.ones(len(uv))])
    rhs = (uv**2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(design, rhs, rcond=None)
    centre2 = sol[:2] / 2
    radius = math.sqrt(max(float(sol[2] + centre2 @ centre2), 0.0))
    resid = np.linalg.norm(uv - centre2, axis=1) - radius
    return origin + basis @ centre2, radius, float(np.sqrt(np.mean(resid**2)))


def offset_across(p: FloatArray, q: FloatArray, axis: FloatArray) -> float:
    """Distance between two points measured across ``axis``."""
    d = q - p
    return float(np.linalg.norm(d - np.dot(d, axis) * axis))


@dataclass(frozen=True)
class Cylinder:
    """A cylinder fitted to points: unit axis, a point of the axis line, radius (mm), rms
    radial residual (mm) and its points (indices into the cloud it was fitted to)."""

    axis: FloatArray
    centre: FloatArray
    radius: float
    rms: float
    members: npt.NDArray[np.int64]


def fit_cylinders(points: FloatArray, normals: FloatArray, spacing: float,
                  cfg: FeatureConfig = DEFAULT_FEATURES) -> list[Cylinder]:
    """Up to ``cfg.max_cylinders`` cylinders of the points (mm, normals of any sign), each
    holding at least ``cfg.min_contact`` points, by falling support. Deterministic: the
    hypotheses are drawn with a generator seeded by the number of points."""
    n = len(points)
    out: list[Cylinder] = []
    if n < cfg.min_contact:
        return out
    eps = max(cfg.plane_eps_mm, 0.5 * spacing)
    sin_n = math.sin(math.radians(cfg.cylinder_normal_deg))
    rng = np.random.default_rng(n)
    free = np.ones(n, dtype=bool)
    for _ in range(cfg.max_cylinders):
        idx = np.flatnonzero(free)
        if len(idx) < cfg.min_contact:
            break
        pairs = idx[rng.integers(0, len(idx), size=(cfg.cylinder_hypotheses, 2))]
        axes, centres, radii, valid = _cylinders_through(points[pairs[:, 0]],
                                                         normals[pairs[:, 0]],
                                                         points[pairs[:, 1]],
                                                         normals[pairs[:, 1]])
        if not valid.any():
            break
        held = free & _on_cylinders(points, normals, axes[valid], centres[valid],
                                    radii[valid], eps, sin_n)
        counts = held.sum(axis=1)
        best = int(np.argmax(counts))  # the first of the most supported
        if counts[best] < cfg.min_contact:
            break
        members = np.flatnonzero(held[best])
        axis, _ = axis_of(normals[members])
        centre, radius, rms = circle(points[members], axis)
        first = Cylinder(axis, centre, radius, rms, members)
        out.append(refine_cylinder(first, points[members]) if cfg.refine_cylinders else first)
        free[members] = False
    return out


def refine_cylinder(cylinder: Cylinder, points: FloatArray) -> Cylinder:
    """The cylinder refitted to its points (mm) by least squares on their distances from its
    surface (axis direction, axis line, radius), from its first estimate; the first estimate
    where the refit does not lower the rms residual.

    The first estimate takes its axis from the points' normals, which local PCA tilts by
    degrees on a short arc of a few points, so the two faces of an exact concentric mate came
    out 5-10 degrees apart (held-out assemblies, CAD samples: median 9 degrees); the refit
    lies on the points themselves."""
    if len(points) < 6:
        return cylinder
    basis = across(cylinder.axis)

    def unpack(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        axis = cylinder.axis + basis @ x[:2]
        return axis / np.linalg.norm(axis), cylinder.centre + basis @ x[2:4]

    def residual(x: FloatArray) -> FloatArray:
        axis, centre = unpack(x)
        d = points - centre
        out: FloatArray = np.linalg.norm(d - np.outer(d @ axis, axis), axis=1) - x[4]
        return out

    from scipy.optimize import least_squares

    start = np.array([0.0, 0.0, 0.0, 0.0, cylinder.radius])
    fit = least_squares(residual, start, method="lm", max_nfev=200)
    rms = float(np.sqrt(np.mean(fit.fun**2)))
    if not (np.all(np.isfinite(fit.x)) and rms < cylinder.rms):
        return cylinder
    axis, centre = unpack(fit.x)
    return Cylinder(axis, centre, abs(float(fit.x[4])), rms, cylinder.members)


def _cylinders_through(p: FloatArray, n: FloatArray, q: FloatArray, m: FloatArray
                       ) -> tuple[FloatArray, FloatArray, FloatArray, npt.NDArray[np.bool_]]:
    """(axes (h, 3), centres (h, 3), radii (h,), valid (h,)) of the cylinders through pairs of
    points (h, 3) with these normals; not valid where the normals are too near parallel to fix
    an axis."""
    axes = np.cross(n, m)
    norms = np.linalg.norm(axes, axis=1)
    valid = norms >= math.sin(math.radians(10.0))
    axes = axes / np.where(valid, norms, 1.0)[:, None]
    # the two normal lines, projected on the plane across the axis, meet at the centre: the
    # least-squares t of t n2 - s m2 = (q - p) across the axis (its normal equations)
    n2 = n - np.sum(n * axes, axis=1, keepdims=True) * axes
    m2 = m - np.sum(m * axes, axis=1, keepdims=True) * axes
    rhs = q - p
    rhs = rhs - np.sum(rhs * axes, axis=1, keepdims=True) * axes
    nn, mm_, nm = np.sum(n2 * n2, axis=1), np.sum(m2 * m2, axis=1), np.sum(n2 * m2, axis=1)
    nr, mr = np.sum(n2 * rhs, axis=1), np.sum(m2 * rhs, axis=1)
    det = nn * mm_ - nm * nm
    t = (nr * mm_ - nm * mr) / np.where(valid, det, 1.0)
    centres = p + t[:, None] * n2
    radii = 0.5 * (_across(p - centres, axes) + _across(q - centres, axes))
    return axes, centres, radii, valid


def _across(d: FloatArray, axes: FloatArray) -> FloatArray:
    """(h,) the lengths of vectors (h, 3) across their axes (h, 3)."""
    out: FloatArray = np.linalg.norm(d - np.sum(d * axes, axis=1, keepdims=True) * axes, axis=1)
    return out


def _on_cylinders(points: FloatArray, normals: FloatArray, axes: FloatArray,
                  centres: FloatArray, radii: FloatArray, eps: float, sin_n: float
                  ) -> npt.NDArray[np.bool_]:
    """(h, n) which points lie on each of h cylinders: within ``eps`` of its surface, their
    normals within ``asin(sin_n)`` of across its axis."""
    along = points @ axes.T - np.sum(centres * axes, axis=1)  # (n, h)
    squared = (np.sum(points ** 2, axis=1)[:, None] - 2 * points @ centres.T
               + np.sum(centres ** 2, axis=1)[None, :] - along ** 2)
    radial = np.sqrt(np.maximum(squared, 0.0))
    on: npt.NDArray[np.bool_] = ((np.abs(radial - radii) <= eps)
                                 & (np.abs(normals @ axes.T) <= sin_n)).T
    return on


def dominant_direction(part: PartCloud,
                       cfg: FeatureConfig = DEFAULT_FEATURES) -> tuple[FloatArray | None, float]:
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
