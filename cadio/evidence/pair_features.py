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
  normals line up with it, its extent) summarises its flat points; an axis fitted to its
  normals, and a circle of each part's contact points about that axis (offset of the two
  centres, radii, residual), is the evidence of a concentric mate, with each part's own axis
  beside it (a mate needs a cylinder on both sides);
- the **face pair**: the evidence of a coincident mate as the CAD defines one, planar faces
  facing each other, touching, with overlap. Of every two fitted planes, one of each part,
  near parallel and with points within reach of each other, the one with the most overlap,
  preferring those whose parts lie on opposite sides of it: its angle, the offset between
  the two planes, the overlap's area and whether the parts are opposed. One plane through the
  whole contact region mixes faces of other orientations and misses most mates (the held-out
  assemblies' coincident mates had residuals of 0.3-8 mm there);
- each part's **axis** (of its curved points' normals, with a circle about it): two parts
  stacked on one axis are coaxial without any nearby cylinder pair;
- each part's **dominant plane direction**: the normal direction carrying the most planar
  points (points sample area uniformly on CAD surfaces; a scan weighs them as it saw them),
  with its ratio to the runner-up, and the angle between the two parts' directions.

Normals come from local PCA of each cloud, except for the CAD samples of the ``truth`` input,
which bring the exact normals of their faces (``cadio.evidence.cad_samples``): there a plane
holds only points of one normal, so no strip of a large cylinder passes for one, and two faces
are opposed when their outward normals meet (``face_pairs``). Every feature is symmetric in
(a, b), so a pair and its swap get the same vector. Lengths are millimetres of
the parts (the capture's metres over its scale), angles degrees; a feature that could not be
measured takes the value of "far" (90 degrees, 1000 mm) and its ``*_found`` flag is 0.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from pykdtree.kdtree import KDTree

from cadio.evidence.fits import (
    DEFAULT_FEATURES,
    Cylinder,
    FeatureConfig,
    PartCloud,
    axis_of,
    circle,
    dominant_direction,
    fit_cylinders,
    offset_across,
    part_cloud,
)
from cadio.records import FloatArray
from cadio.tolerances import DEFAULT_TOLERANCES

__all__ = [
    "N_PAIR_FEATURES",
    "PAIR_FEATURES",
    "FeatureConfig",
    "PartCloud",
    "dominant_direction",
    "encode_features",
    "evidence_digest",
    "pair_features",
    "pair_features_many",
    "part_cloud",
]

PAIR_FEATURES = (
    "gap_mm", "contact_min", "contact_max",
    "contact_plane_found", "contact_plane_rms_mm", "contact_plane_normal", "contact_extent_mm",
    "contact_axis_found", "contact_axis_flatness", "contact_axis_offset_mm",
    "contact_radius_diff_mm", "contact_circle_rms_mm",
    "axis_found", "axis_angle_deg", "axis_offset_mm",
    "dom_found", "dom_angle_deg", "dom_ratio",
    "spacing_mm",
    "contact_axis_worse_flatness", "contact_axis_angle_deg",
    "face_found", "face_angle_deg", "face_offset_mm", "face_overlap_mm2", "face_opposed",
    "cyl_found", "cyl_angle_deg", "cyl_offset_mm", "cyl_radius_diff_mm", "cyl_support",
    # appended: a checkpoint reads its columns by name, and one trained before reads its own
    "coax_found", "coax_spread_mm", "coax_normal_deg", "coax_face_gap_mm",
)
N_PAIR_FEATURES = len(PAIR_FEATURES)
FAR_DEG, FAR_MM = 90.0, 1000.0


def evidence_digest() -> str:
    """SHA-256 of the pair evidence's code (this module, ``fits`` and ``cad_samples``). What
    the evidence measured is stored (a relation dataset) or cached (a night's related pair
    views), so a change of its code must rebuild them rather than reuse vectors of another
    meaning."""
    from cadio.evidence import cad_samples, fits

    digest = hashlib.sha256()
    for source in (cad_samples.__file__, fits.__file__, __file__):
        digest.update(Path(source or "").read_bytes())
    return digest.hexdigest()


def _angle_deg(u: FloatArray, v: FloatArray) -> float:
    """The angle between two unit directions whose sign is arbitrary, in [0, 90] degrees."""
    return math.degrees(math.acos(min(1.0, abs(float(u @ v)))))


@dataclass(frozen=True)
class FacePair:
    """Two fitted planes, one of each part, facing each other within reach (see
    ``face_pairs``)."""

    angle_deg: float
    offset_mm: float
    area_mm2: float
    opposed: float


@dataclass(frozen=True)
class CylinderPair:
    """Two fitted cylinders, one of each part's contact region (see ``cylinder_pairs``)."""

    angle_deg: float
    offset_mm: float
    radius_diff_mm: float
    support: float
    # the other cylinder's points measured about the better-supported one's axis
    spread_mm: float
    normal_deg: float
    face_gap_mm: float


def pair_features(a: PartCloud, b: PartCloud,
                  cfg: FeatureConfig = DEFAULT_FEATURES) -> npt.NDArray[np.float32]:
    """(``N_PAIR_FEATURES``,) the pair's evidence, in ``PAIR_FEATURES`` order."""
    if len(a.points) == 0 or len(b.points) == 0:
        out = np.array([FAR_MM, 0, 0, 0, FAR_MM, 0, 0, 0, 0, FAR_MM, FAR_MM, FAR_MM,
                        0, FAR_DEG, FAR_MM, 0, FAR_DEG, 0, 0, 1.0, FAR_DEG, *NO_FACE_PAIR,
                        *NO_CYLINDER_PAIR, *NO_COAXIAL_PAIR],
                       dtype=np.float32)
        return out
    reach = cfg.contact_mm + cfg.contact_spacings * max(a.spacing, b.spacing)
    da = b.tree.query(a.points, k=1, distance_upper_bound=_inclusive(reach))[0]
    db = a.tree.query(b.points, k=1, distance_upper_bound=_inclusive(reach))[0]
    in_a, in_b = da <= reach, db <= reach
    shares = sorted((float(in_a.mean()), float(in_b.mean())))
    feats = [min(float(da.min()), float(db.min())) if in_a.any() else _least_distance(a, b),
             *shares]
    feats += _contact_plane(a, b, in_a, in_b, cfg)
    feats += _contact_axis(a, b, in_a, in_b, cfg)
    feats += _part_axes(a, b, cfg)
    feats += _dominant_pair(a, b, cfg)
    feats.append(max(a.spacing, b.spacing))
    feats += _contact_axes_apart(a, b, in_a, in_b, cfg)
    feats += _face_pair(face_pairs(a, b, reach, cfg), exact=a.exact and b.exact)
    cylinders = cylinder_pairs(a, b, in_a, in_b, cfg)
    feats += _cylinder_pair(cylinders)
    feats += _coaxial_pair(cylinders)
    return np.array(feats, dtype=np.float32)


def _least_distance(a: PartCloud, b: PartCloud) -> float:
    """The least distance between the two clouds, exactly, for clouds apart: every point's
    nearest neighbour without a bound is slow where the other cloud is far (the search visits
    every cell about as near), so a few points give an upper bound, and only the points within
    it are searched to the end."""
    bound = float(b.tree.query(a.points[:: max(1, len(a.points) // 64)], k=1)[0].min())
    within = b.tree.query(a.points, k=1, distance_upper_bound=_inclusive(bound))[0]
    return float(within.min())


def _inclusive(bound: float) -> float:
    """A k-d tree's ``distance_upper_bound`` that keeps a point exactly at ``bound`` (the
    tree's bound is exclusive; on a voxel grid such distances occur)."""
    return bound * (1 + 1e-9) + 1e-12


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


def _contact_axis(a: PartCloud, b: PartCloud, in_a: npt.NDArray[np.bool_],
                  in_b: npt.NDArray[np.bool_], cfg: FeatureConfig) -> list[float]:
    """(found, flatness, offset of the circle centres, radius difference, worse circle rms) of
    the contact region's curved points about the axis their normals share. The axis is taken
    from the part whose curved contact points agree best on one (a shaft's many points rather
    than the few of the bore around it), and each part's points get a circle about it."""
    curved_a, curved_b = in_a & ~a.planar, in_b & ~b.planar
    if curved_a.sum() < cfg.min_contact or curved_b.sum() < cfg.min_contact:
        return [0.0, 0.0, FAR_MM, FAR_MM, FAR_MM]
    axis, flat = min((axis_of(a.normals[curved_a]), axis_of(b.normals[curved_b])),
                     key=lambda fit: fit[1])
    ca, ra, ea = circle(a.points[curved_a], axis)
    cb, rb, eb = circle(b.points[curved_b], axis)
    return [1.0, flat, offset_across(ca, cb, axis), abs(ra - rb), max(ea, eb)]


def _contact_axes_apart(a: PartCloud, b: PartCloud, in_a: npt.NDArray[np.bool_],
                        in_b: npt.NDArray[np.bool_], cfg: FeatureConfig) -> list[float]:
    """(the worse flatness, the angle between the axes) of each part's own contact axis. A
    concentric mate needs a cylinder or cone on *both* sides sharing one axis; the shared fit
    of ``_contact_axis`` takes the better part's axis, which a cap of a sphere or the edge of a
    flat part against a cylinder also fits."""
    curved_a, curved_b = in_a & ~a.planar, in_b & ~b.planar
    if curved_a.sum() < cfg.min_contact or curved_b.sum() < cfg.min_contact:
        return [1.0, FAR_DEG]
    (ua, fa), (ub, fb) = axis_of(a.normals[curved_a]), axis_of(b.normals[curved_b])
    return [max(fa, fb), _angle_deg(ua, ub)]


# The face pair's values when no two planes of the parts face each other within reach.
NO_FACE_PAIR = (0.0, FAR_DEG, FAR_MM, 0.0, 0.0)
FACE_PAIR_DEG = 10.0  # planes of the two parts further apart than this are no face pair


def _face_pair(faces: Sequence[FacePair], exact: bool = False) -> list[float]:
    """(found, angle, offset, overlap area, opposed) of the best face pair: the opposed one
    (then any) with the largest overlap. ``exact``: the planes are the faces' own (CAD
    samples), and a pair of them touching within the CAD's contact tolerance comes first
    among the opposed: a caster's fork rests on its plate on two narrow faces beside a wider
    pair 2 mm apart."""
    if not faces:
        return list(NO_FACE_PAIR)
    touch = DEFAULT_TOLERANCES.contact_mm

    def rank(f: FacePair) -> tuple[float, bool, float]:
        return f.opposed, exact and f.offset_mm <= touch, f.area_mm2

    best = max(faces, key=rank)
    return [1.0, best.angle_deg, best.offset_mm, best.area_mm2, best.opposed]


def face_pairs(a: PartCloud, b: PartCloud, reach: float,
               cfg: FeatureConfig = DEFAULT_FEATURES) -> list[FacePair]:
    """Every face pair: a fitted plane of each part, the two within ``FACE_PAIR_DEG`` of
    parallel, with at least ``min_contact`` points of each within ``reach`` of the other
    plane's points (the overlap). The coincident mate of the CAD is such a pair: planar faces
    with opposite outward normals, touching, with overlap.

    angle: between the plane normals (degrees); offset: the distance between the two planes
    along their mean normal at the overlap (mm); overlap: the smaller of the two parts'
    overlapping points times their spacing squared (mm^2); opposed: 1 when the parts' other
    points near the overlap lie on opposite sides of it (the faces rest against each other),
    0 when on one side (flush side by side), 0.5 when a part shows no such points. Where both
    clouds bring exact normals (outward, ``cadio.evidence.cad_samples``), 1 when the two faces'
    outward normals meet and 0 when they agree: the sides of the points read a block resting
    in a pocket as flush, the pocket's walls standing on the block's side of the floor.
    """
    out = []
    cos = math.cos(math.radians(FACE_PAIR_DEG))
    members_b = b.plane_members()
    trees: dict[int, KDTree] = {}
    for i, ia in enumerate(a.plane_members()):
        na = a.planes[i][0]
        for j, ib in enumerate(members_b):
            nb = b.planes[j][0]
            if abs(float(na @ nb)) < cos or len(ia) < cfg.min_contact \
                    or len(ib) < cfg.min_contact:
                continue
            if j not in trees:
                trees[j] = KDTree(np.asarray(b.points[ib], dtype=np.float64))
            near_a = ia[trees[j].query(np.asarray(a.points[ia], dtype=np.float64), k=1)[0]
                        <= reach]
            if len(near_a) < cfg.min_contact:
                continue
            near_b = ib[KDTree(np.asarray(a.points[ia], dtype=np.float64)).query(
                np.asarray(b.points[ib], dtype=np.float64), k=1)[0] <= reach]
            if len(near_b) < cfg.min_contact:
                continue
            normal = na if na @ nb >= 0 else -na
            normal = (normal + nb) / np.linalg.norm(normal + nb)
            pa, pb = a.points[near_a], b.points[near_b]
            offset = abs(float((pb.mean(axis=0) - pa.mean(axis=0)) @ normal))
            area = min(len(near_a) * a.spacing**2, len(near_b) * b.spacing**2)
            angle = _angle_deg(na, nb)
            # exact normals point out of their parts (see the docstring)
            opposed = (float(na @ nb < 0) if a.exact and b.exact
                       else _opposed(a, b, np.concatenate([pa, pb]), normal, ia, ib))
            out.append(FacePair(angle, offset, area, opposed))
    return out


def _opposed(a: PartCloud, b: PartCloud, overlap: FloatArray, normal: FloatArray,
             on_a: npt.NDArray[np.int64], on_b: npt.NDArray[np.int64]) -> float:
    """Whether the two parts' points near the overlap (within its radius plus two spacings,
    off the face pair's planes) lie on opposite sides of it: 1, 0, or 0.5 when either part has
    no such point."""
    centre = overlap.mean(axis=0)
    radius = float(np.max(np.linalg.norm(overlap - centre, axis=1)))
    sides = []
    for part, on in ((a, on_a), (b, on_b)):
        r = radius + 2.0 * part.spacing
        near = np.flatnonzero(np.linalg.norm(part.points - centre, axis=1) <= r)
        near = near[~np.isin(near, on)]
        if len(near) == 0:
            return 0.5
        d = (part.points[near] - centre) @ normal
        sides.append(float(np.median(d)))
    return 1.0 if sides[0] * sides[1] < 0 else 0.0


# The cylinder pair's values when either part shows no cylinder in the contact region.
NO_CYLINDER_PAIR = (0.0, FAR_DEG, FAR_MM, FAR_MM, 0.0)


def _cylinder_pair(cylinders: Sequence[CylinderPair]) -> list[float]:
    """(found, angle, offset, radius difference, support) of the most coaxial cylinder pair:
    the least offset among those within ``FACE_PAIR_DEG`` of parallel (else the least
    angle)."""
    if not cylinders:
        return list(NO_CYLINDER_PAIR)
    best = min(cylinders, key=lambda c: (c.angle_deg > FACE_PAIR_DEG,
                                         c.offset_mm if c.angle_deg <= FACE_PAIR_DEG
                                         else c.angle_deg))
    return [1.0, best.angle_deg, best.offset_mm, best.radius_diff_mm, best.support]


# The coaxial pair's values when either part shows no cylinder in the contact region.
NO_COAXIAL_PAIR = (0.0, FAR_MM, FAR_DEG, FAR_MM)
COAXIAL_SPREAD_MM = 1.0  # a pair whose points spread more about the axis is not coaxial


def _coaxial_pair(cylinders: Sequence[CylinderPair]) -> list[float]:
    """(found, spread, normal angle, face gap) of the cylinder pair whose faces lie nearest
    among the coaxial ones (within ``FACE_PAIR_DEG`` of radial normals and
    ``COAXIAL_SPREAD_MM`` of spread), else the least spread: the evidence of a concentric mate
    as the CAD defines one, coaxial faces within 1 mm of each other. Unlike the pair of
    ``_cylinder_pair``, the faces' distance is their own, not the parts' (six bolts of a pipe
    flange stand coaxial over its holes, 1.59 mm above them, while their washers touch it)."""
    if not cylinders:
        return list(NO_COAXIAL_PAIR)

    def coaxial(c: CylinderPair) -> bool:
        return c.normal_deg <= FACE_PAIR_DEG and c.spread_mm <= COAXIAL_SPREAD_MM

    best = min(cylinders, key=lambda c: (not coaxial(c),
                                         c.face_gap_mm if coaxial(c) else c.spread_mm))
    return [1.0, best.spread_mm, best.normal_deg, best.face_gap_mm]


def about_axis(ref: Cylinder, ref_points: FloatArray, points: FloatArray, normals: FloatArray
               ) -> tuple[float, float, float]:
    """(spread, normal angle, face gap) of one cylinder's points (mm) and unit normals about
    another's axis (``ref``, fitted to ``ref_points``). spread: the rms of their distances
    from the axis about the median (0 on a coaxial cylinder, whatever the arc they cover);
    normal angle: the mean angle (degrees, sign-free) between their normals and the radial
    direction; face gap: the distance of the two faces, the radius difference and the gap
    between the two point sets along the axis, combined (0 where they overlap)."""
    radial, along = _about(ref, points)
    dist = np.linalg.norm(radial, axis=1)
    spread = float(np.sqrt(np.mean((dist - np.median(dist)) ** 2)))
    unit = radial / np.maximum(dist, 1e-12)[:, None]
    cos = np.clip(np.abs(np.sum(unit * normals, axis=1)), 0.0, 1.0)
    normal = float(np.degrees(np.arccos(cos)).mean())
    ref_radial, ref_along = _about(ref, ref_points)
    ref_dist = np.linalg.norm(ref_radial, axis=1)
    axial = max(0.0, float(max(along.min(), ref_along.min()) - min(along.max(), ref_along.max())))
    return spread, normal, math.hypot(float(np.median(dist) - np.median(ref_dist)), axial)


def _about(cylinder: Cylinder, points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(n, 3) each point's offset from the cylinder's axis line, across it, and (n,) its
    position along the axis."""
    rel = points - cylinder.centre
    along = rel @ cylinder.axis
    return rel - np.outer(along, cylinder.axis), along


def cylinder_pairs(a: PartCloud, b: PartCloud, in_a: npt.NDArray[np.bool_],
                   in_b: npt.NDArray[np.bool_],
                   cfg: FeatureConfig = DEFAULT_FEATURES) -> list[CylinderPair]:
    """Every pair of cylinders, one fitted to each part's curved contact points (``in_a``,
    ``in_b``): the evidence of a concentric mate as the CAD defines one (a coaxial face of each
    part, within 1 mm). A pin against a race's side, or two balls, touch along curved faces
    whose axes lie apart.

    angle: between the axes (degrees); offset: the larger distance of either axis point from
    the other axis line (mm); support: the smaller of the two cylinders' point counts over
    their part's contact points."""
    curved_a, curved_b = np.flatnonzero(in_a & ~a.planar), np.flatnonzero(in_b & ~b.planar)
    cyl_a = fit_cylinders(a.points[curved_a], a.normals[curved_a], a.spacing, cfg)
    cyl_b = fit_cylinders(b.points[curved_b], b.normals[curved_b], b.spacing, cfg)
    out = []
    for ca in cyl_a:
        for cb in cyl_b:
            angle = _angle_deg(ca.axis, cb.axis)
            offset = max(offset_across(ca.centre, cb.centre, ca.axis),
                         offset_across(cb.centre, ca.centre, cb.axis))
            support = min(len(ca.members) / max(int(in_a.sum()), 1),
                          len(cb.members) / max(int(in_b.sum()), 1))
            pa, pb = a.points[curved_a][ca.members], b.points[curved_b][cb.members]
            na, nb = a.normals[curved_a][ca.members], b.normals[curved_b][cb.members]
            # the better-supported cylinder gives the axis: a bore's few points about a
            # shaft's many, however short the arc they cover
            about = (about_axis(ca, pa, pb, nb) if len(ca.members) >= len(cb.members)
                     else about_axis(cb, pb, pa, na))
            out.append(CylinderPair(angle, offset, abs(ca.radius - cb.radius), support, *about))
    return out


def _part_axes(a: PartCloud, b: PartCloud, cfg: FeatureConfig) -> list[float]:
    """(found, angle between the parts' axes, offset of their circle centres across them)."""
    axes = []
    for part in (a, b):
        curved = ~part.planar
        if curved.sum() < cfg.min_contact:
            return [0.0, FAR_DEG, FAR_MM]
        axis, _ = axis_of(part.normals[curved])
        centre, _, _ = circle(part.points[curved], axis)
        axes.append((axis, centre))
    (ua, pa), (ub, pb) = axes
    angle = _angle_deg(ua, ub)
    mean = ua if ua @ ub >= 0 else -ua
    mean = (mean + ub) / np.linalg.norm(mean + ub)
    return [1.0, angle, offset_across(pa, pb, mean)]


def _dominant_pair(a: PartCloud, b: PartCloud, cfg: FeatureConfig) -> list[float]:
    """(found, angle between the dominant directions in [0, 90], the smaller ratio)."""
    da, ra = dominant_direction(a, cfg)
    db, rb = dominant_direction(b, cfg)
    if da is None or db is None:
        return [0.0, FAR_DEG, 0.0]
    return [1.0, _angle_deg(da, db), min(ra, rb)]


# How each feature enters a network: lengths as log1p(mm) (a tenth of a millimetre and a metre
# both stay in range), angles over 90 degrees, flags, shares and ratios as they are (ratios over
# their cap).
_LENGTH = {i for i, n in enumerate(PAIR_FEATURES) if n.endswith(("_mm", "_mm2"))}
_ANGLE = {i for i, n in enumerate(PAIR_FEATURES) if n.endswith("_deg")}
_RATIO = {PAIR_FEATURES.index("dom_ratio")}


def encode_features(features: npt.NDArray[np.floating],
                    cfg: FeatureConfig = DEFAULT_FEATURES) -> npt.NDArray[np.float32]:
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
                       cloud: Callable[[FloatArray, FloatArray | None], PartCloud] | None = None,
                       memo: dict[tuple[Hashable, Hashable], npt.NDArray[np.float32]] | None = None
                       ) -> npt.NDArray[np.float32]:
    """(N, ``N_PAIR_FEATURES``) features of pairs (N, 2, k, 3) in any unit, or of N pairs of
    clouds of any sizes (k_a, 3), (k_b, 3). Every feature is invariant under a rigid motion of
    the pair: the clouds may be in any frame. A cloud of six columns (k, 6) brings each
    point's exact unit normal after its position (``cadio.evidence.cad_samples``).

    Args:
        mm_per_unit: (N,) millimetres of the parts per unit of ``points``.
        keys: per row, a key of each part's cloud: a cloud met again (a part of an assembly in
            many pairs) gets its normals once, and a pair of clouds met again (the CAD samples
            of two parts, the same in every view of them) is measured once.
        cloud: how a part's points (mm) and exact normals (or None) become a ``PartCloud``;
            ``part_cloud`` by default.
        memo: the features of pairs already measured, by their two keys, read and filled here
            (shared by calls whose keys name the same clouds); with ``keys`` only.
    """
    mm = np.broadcast_to(np.asarray(mm_per_unit, dtype=np.float64), (len(points),))
    cache: dict[Hashable, PartCloud] = {}

    def default(pts: FloatArray, normals: FloatArray | None) -> PartCloud:
        return part_cloud(pts, normals=normals)

    fit = cloud or default

    def part(i: int, k: int) -> PartCloud:
        key = (i, k) if keys is None else keys[i][k]
        if key not in cache:
            arr = np.asarray(points[i][k], dtype=np.float64)
            cache[key] = fit(arr[..., :3] * mm[i], arr[..., 3:6] if arr.shape[-1] == 6 else None)
        return cache[key]

    measured: dict[tuple[Hashable, Hashable], npt.NDArray[np.float32]] = \
        {} if memo is None else memo
    out = np.zeros((len(points), N_PAIR_FEATURES), dtype=np.float32)
    for i in range(len(points)):
        if keys is None:
            out[i] = pair_features(part(i, 0), part(i, 1))
            continue
        pair = (keys[i][0], keys[i][1])
        if pair not in measured:
            measured[pair] = pair_features(part(i, 0), part(i, 1))
        out[i] = measured[pair]
    return out
