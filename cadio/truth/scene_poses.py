"""Poses of a scene pair: directional, parallel and perpendicular from the parts' features,
coaxial from what they offer (ends, bores).

A directional pair puts a's centroid off b's along a direction at a chosen angle from the
relation's axis, clear of b's box; a parallel pair turns both dominant plane directions
vertical and stacks the parts apart; a perpendicular pair turns b's horizontal. A coaxial pair
nests a shaft in a bore or stacks two ends on one axis, its faces within the concentric gap (a
mate) or beyond it (a clearance pair). Near-boundary pairs (``side``) sit just inside or
outside the cone, the angle or the coaxial tolerance. The scenes stage (``cadio.truth.scenes``)
chooses the parts and labels the placed pair with the truth.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from cadio.records import DIRECTIONAL, Features, FloatArray, Relation
from cadio.truth.placement import (
    Nested,
    Offers,
    Stacked,
    align,
    coaxial_choices,
    nest,
    pose,
    rotation,
    spin,
    stack,
    tilt,
)
from cadio.truth.relations import direction_axes
from cadio.truth.scene_config import SceneConfig

INSIDE, OUTSIDE = "inside", "outside"  # the sides of a near-boundary pair
_Z = np.array([0.0, 0.0, 1.0])


def directional(a: Features, b: Features, relation: Relation, side: str,
                rng: np.random.Generator, cfg: SceneConfig) -> tuple[FloatArray, FloatArray]:
    """a's centroid off b's along a direction at a chosen angle from the relation's axis."""
    ra, rb = spin(rng), spin(rng)
    a0, b0 = a.transformed(pose(ra)), b.transformed(pose(rb))
    axis = direction_axes(cfg.view_axis)[DIRECTIONAL.index(relation)]
    cone, margin = cfg.tolerances.direction_cone_deg, cfg.near_directional_deg
    if side:
        theta = cone - margin if side == INSIDE else cone + margin
    else:  # uniform over the spherical cap of half-angle cone - margin
        theta = math.degrees(math.acos(rng.uniform(math.cos(math.radians(cone - margin)), 1)))
    u = tilt(axis, theta, rng)
    t = _separation(_rel_box(a0), _rel_box(b0), u) + rng.uniform(*cfg.gap_mm)
    return pose(ra, t * u - a0.centroid), pose(rb, -b0.centroid)


def parallel_or_perpendicular(a: Features, b: Features, relation: Relation, side: str,
                              rng: np.random.Generator,
                              cfg: SceneConfig) -> tuple[FloatArray, FloatArray]:
    """a's dominant normal vertical; b's vertical (parallel) or horizontal (perpendicular)."""
    assert a.dominant_plane is not None and b.dominant_plane is not None
    near = cfg.tolerances.parallel_deg + (
        -cfg.near_plane_deg if side == INSIDE else cfg.near_plane_deg)
    ra = spin(rng) @ align(a.dominant_plane, _Z * rng.choice([-1.0, 1.0]))
    if relation is Relation.PARALLEL:
        turn = rotation(tilt(_Z, 90.0, rng), near) if side else np.eye(3)
        rb = spin(rng) @ turn @ align(b.dominant_plane, _Z * rng.choice([-1.0, 1.0]))
    else:  # normal to +X, raised by the near-boundary elevation, then spun about Z
        raise_ = rotation(np.array([0.0, 1.0, 0.0]), -near) if side else np.eye(3)
        rb = spin(rng) @ raise_ @ align(b.dominant_plane, np.array([1.0, 0.0, 0.0]))
    a0, b0 = a.transformed(pose(ra)), b.transformed(pose(rb))
    if relation is Relation.PARALLEL:  # stacked: disjoint heights, so no face touches
        za, zb = stack_heights(a0, b0, rng, cfg)
        shift = _lateral(a0, b0, rng)
        return pose(ra, np.array([0.0, 0.0, za]) - a0.centroid * [1, 1, 0] + shift), \
            pose(rb, np.array([0.0, 0.0, zb]) - b0.centroid * [1, 1, 0])
    u = tilt(_Z, math.degrees(math.acos(rng.uniform(-1.0, 1.0))), rng)
    t = _separation(_rel_box(a0), _rel_box(b0), u) + rng.uniform(*cfg.gap_mm)
    return pose(ra, t * u - a0.centroid), pose(rb, -b0.centroid)


def _rel_box(f: Features) -> tuple[FloatArray, FloatArray]:
    """The bounding box relative to the centroid, mm."""
    return f.bbox_min - f.centroid, f.bbox_max - f.centroid


def _separation(box_a: tuple[FloatArray, FloatArray], box_b: tuple[FloatArray, FloatArray],
                u: FloatArray) -> float:
    """Smallest t >= 0 (mm) such that box_a moved by t*u no longer overlaps box_b."""
    ts: list[float] = []
    for k in range(3):
        if u[k] > 1e-9:
            ts.append(float((box_b[1][k] - box_a[0][k]) / u[k]))
        elif u[k] < -1e-9:
            ts.append(float((box_b[0][k] - box_a[1][k]) / u[k]))
    return max(0.0, min(ts))


def stack_heights(a0: Features, b0: Features, rng: np.random.Generator,
                  cfg: SceneConfig) -> tuple[float, float]:
    """Z shifts (mm) putting one box above the other (random order) with a random gap."""
    gap = rng.uniform(*cfg.gap_mm)
    if rng.random() < 0.5:  # a on top
        return float(b0.bbox_max[2] - a0.bbox_min[2] + gap), 0.0
    return 0.0, float(a0.bbox_max[2] - b0.bbox_min[2] + gap)


def _lateral(a0: Features, b0: Features, rng: np.random.Generator) -> FloatArray:
    """A random horizontal shift (mm) within half the parts' combined footprint."""
    half = 0.25 * ((a0.bbox_max - a0.bbox_min) + (b0.bbox_max - b0.bbox_min))
    return np.array([rng.uniform(-half[0], half[0]), rng.uniform(-half[1], half[1]), 0.0])


def coaxial(found: Sequence[Offers], features: Sequence[Features], side: str,
            rng: np.random.Generator, cfg: SceneConfig,
            apart: tuple[float, float] | None = None) -> tuple[int, int, FloatArray, FloatArray]:
    """Two parts on one axis: their indices in ``found`` (what each part offers) and
    ``features``, and their poses. Nested where a shaft fits a bore and the parts do not
    interfere (plain pairs), else stacked end to end; near-boundary pairs are stacked with the
    upper axis shifted just inside or outside ``coaxial_mm``. Where no radii match, two ends
    are stacked all the same, and parts without two ends are stacked apart (the truth says
    what that makes).

    ``apart``: None for a concentric mate (ends at most ``gap_fraction`` of
    ``concentric_gap_mm`` apart, shafts at most ``nest_fraction`` of it thinner than their
    bore); (low, high) mm for a clearance pair (shafts low to high thinner than their bore,
    ends low to high apart along the axis).
    """
    gap = cfg.tolerances.concentric_gap_mm
    if apart is None:
        choice = coaxial_choices(found, cfg.stack_fraction * gap, cfg.nest_fraction * gap, rng,
                                 nests=not side)
    else:
        choice = coaxial_choices(found, cfg.stack_fraction * gap, apart[1], rng,
                                 nest_min_mm=apart[0])
    if isinstance(choice, Nested):
        placed = nest(found[choice.i], choice.hole, found[choice.j], choice.shaft, rng)
        if placed is not None:
            return choice.i, choice.j, *placed
        # the parts interfere however the shaft sits: stack two parts instead
        choice = coaxial_choices(found, cfg.stack_fraction * gap, 0.0, rng, nests=False)
    if isinstance(choice, Stacked):
        i, j, end_i, end_j = choice.i, choice.j, choice.first, choice.second
    else:
        with_ends = [k for k, o in enumerate(found) if o.ends]
        if len(with_ends) < 2:
            i, j = two(list(range(len(found))), rng)
            za, zb = stack_heights(features[i], features[j], rng, cfg)
            return i, j, pose(np.eye(3), [0.0, 0.0, za]), pose(np.eye(3), [0.0, 0.0, zb])
        i, j = two(with_ends, rng)
        end_i = found[i].ends[int(rng.integers(len(found[i].ends)))]
        end_j = found[j].ends[int(rng.integers(len(found[j].ends)))]
    if apart is not None:
        lift = float(rng.uniform(*apart))
    else:
        room = max(0.0, (cfg.gap_fraction * gap) ** 2 - (end_i.radius - end_j.radius) ** 2)
        lift = 0.0 if side else float(rng.uniform(0.0, math.sqrt(room)))
    shift = near_factor(side, cfg) * cfg.tolerances.coaxial_mm
    return i, j, *stack(found[i], end_i, found[j], end_j, lift, shift, rng)


def two(choices: Sequence[int], rng: np.random.Generator) -> tuple[int, int]:
    """Two different members of ``choices`` (at least two)."""
    i = int(rng.integers(len(choices)))
    j = (i + 1 + int(rng.integers(len(choices) - 1))) % len(choices)
    return choices[i], choices[j]


def near_factor(side: str, cfg: SceneConfig) -> float:
    """How far a near-boundary pair of ``side`` sits from a tolerance, in tolerances."""
    return {"": 0.0, INSIDE: cfg.near_inside_factor, OUTSIDE: cfg.near_outside_factor}[side]
