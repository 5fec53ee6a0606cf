"""Assembly families of face contacts: a bar in a guide groove, carriages on a rail, a key in a
keyway (all slide), and a ring cut into segments that rest end to end.

A slider is what two planar contacts whose normals are not parallel leave free: one translation
(``cadio.truth.joints``). The other families slide nowhere (a bolt under its head turns, a
pillow block rests), so without these the corpus held 46 slider pairs in 10,714 pair views and
the relation networks never answered one, while real assemblies slide often: a rack in its
guide, a mount in a frame's slot, a carriage on a rail, a hub's key in a shaft's keyway.

Each family also draws the near misses that make the joint a question of geometry, not of the
family: a bar narrower than its groove touches one wall (still a slider) or a loose carriage
rides on the rail's top alone (planar), a standard key leaves its hub's slot ceiling 0.3 mm
clear (planar: the key's sides only), a hub against a shaft shoulder turns (revolute) where
one without it also slides (cylindrical). A segmented ring (a split collar, a segmented cage)
is the planar joint of parts that share an axis: the corpus's other planar pairs rest on a
plate, so a network read the segments of a bearing's cage as turning on one cylinder. Key
sizes follow DIN 6885-1 (width, height and the shaft's keyway depth t1 per shaft diameter).
Each ``draw_*`` takes a seeded generator and returns a ``Design``.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import build123d as bd
import numpy as np

from cadio.samples.assembly_kit import (
    BODY_COLOURS,
    FASTENERS,
    MOTION,
    NO_CATEGORY,
    TO_X,
    Design,
    Mate,
    PartSpec,
    fit,
    placed,
    seat,
)
from cadio.samples.parts import _box, _cut, _cyl, _fuse, _one, _shaft
from cadio.samples.variants import _pick, _u

# DIN 6885-1 parallel keys: shaft diameter range (mm), key width b, height h, shaft depth t1,
# hub depth t2 (t1 + t2 exceeds h by the standard's top clearance).
_KEYS = ((10, 12, 4, 4, 2.5, 1.8), (12, 17, 5, 5, 3.0, 2.3), (17, 22, 6, 6, 3.5, 2.8),
         (22, 30, 8, 7, 4.0, 3.3), (30, 38, 10, 8, 5.0, 3.3), (38, 44, 12, 8, 5.0, 3.3))


# --------------------------------------------------------------------------- guide groove


def draw_slide_guide(rng: np.random.Generator) -> Design:
    """A bar (a rack or a slide) in the rectangular groove of a base, touching the groove's
    floor and both walls or one of them, flush or standing proud; often held down by a cover
    plate screwed over the groove, with a groove of its own where the bar stands proud."""
    length, width = _u(rng, 80, 220, 1.0), _u(rng, 40, 120, 1.0)
    thick = _u(rng, 12, 30)
    gw = _u(rng, 8, min(40.0, width - 20), 0.5)
    gd = _u(rng, 3, thick - 5)
    both = bool(rng.random() < 0.6)
    bw = gw if both else gw - _u(rng, 0.5, min(3.0, gw / 3))
    by = 0.0 if both else (bw - gw) / 2  # against the wall at y = -gw / 2
    covered = bool(rng.random() < 0.6)
    proud = 0.0 if covered and rng.random() < 0.5 else _u(rng, 2, 15)
    bh = gd + proud
    bl = _u(rng, 0.5 * length, 0.9 * length, 1.0)
    bx = _u(rng, -(length - bl) / 2, (length - bl) / 2)
    cl = _u(rng, 0.3 * bl, 0.8 * bl, 1.0)
    ct = _u(rng, proud + 3, proud + 15)

    def base() -> bd.Shape[Any]:
        return _cut(_box(length, width, thick, z=-thick), _box(length + 2, gw, gd + 1, z=-gd))

    def cover() -> bd.Shape[Any]:
        plate = _box(cl, width, ct, x=bx)
        return _cut(plate, _box(cl + 2, gw, proud, x=bx, z=0)) if proud else plate

    parts = [PartSpec("base", _pick(rng, BODY_COLOURS), NO_CATEGORY, base),
             PartSpec("bar", _pick(rng, ("steel", "dark", "brass")), MOTION,
                      lambda: _box(bl, bw, bh, x=bx, y=by, z=-gd))]
    mates = [seat("bar", "base")]
    if covered:
        parts.append(PartSpec("cover", _pick(rng, ("zinc", "red", "alu")), NO_CATEGORY, cover))
        mates += [seat("cover", "base"), seat("cover", "bar")]
    walls = "both walls" if both else "one wall"
    top = "flush" if not proud else f"{proud:g} mm proud"
    return Design(f"bar {bl:g}x{bw:g}x{bh:g} in a {gw:g}x{gd:g} groove ({walls}, {top}), base "
                  f"{length:g}x{width:g}x{thick:g}" + (f", cover {cl:g}x{ct:g}" if covered else ""),
                  tuple(parts), tuple(mates))


# --------------------------------------------------------------------------- rail and carriages


def draw_rail_carriage(rng: np.random.Generator) -> Design:
    """A rectangular rail on a plate (against a locating ledge or not), one or two carriages
    straddling it (channel as wide as the rail, or loose: riding on the top alone) and, over
    two carriages, often a table."""
    rw, rh = _u(rng, 10, 30), _u(rng, 8, 25)
    cl = _u(rng, 1.2 * rw, 3 * rw, 1.0)
    rl = max(_u(rng, 100, 300, 1.0), 4 * cl + 10)  # room for two carriages apart
    ledge = bool(rng.random() < 0.5)
    gap = _u(rng, 2, rh / 2)
    lw, lh = _u(rng, 4, 12), _u(rng, 1, gap - 1)
    side = _u(rng, 5, 15)
    cw = rw + 2 * side
    pw, pl, pt = cw + _u(rng, 20, 80, 1.0), rl + _u(rng, 0, 60, 1.0), _u(rng, 8, 20)
    n = int(rng.integers(1, 3))
    top_t = _u(rng, 5, 15)
    loose = bool(rng.random() < 0.25)
    channel = rw + (_u(rng, 0.5, 2) if loose else 0.0)
    span = rl - cl
    xs = [0.0] if n == 1 else [-span / 2 + _u(rng, 0, span / 4), span / 2 - _u(rng, 0, span / 4)]

    def plate() -> bd.Shape[Any]:
        body = _box(pl, pw, pt, z=-pt)
        return _fuse(body, _box(pl, lw, lh, y=-rw / 2 - lw / 2)) if ledge else body

    def carriage(x: float) -> Any:
        return lambda: _cut(_box(cl, cw, rh - gap + top_t, x=x, z=gap),
                            _box(cl + 2, channel, rh - gap + 1, x=x, z=gap - 1))

    parts = [PartSpec("plate", _pick(rng, BODY_COLOURS), NO_CATEGORY, plate),
             PartSpec("rail", "steel", MOTION, lambda: _box(rl, rw, rh))]
    mates = [seat("rail", "plate")]
    colour = _pick(rng, ("dark", "red", "brass"))
    for k, x in enumerate(xs):
        label = f"carriage-{k + 1}"
        parts.append(PartSpec(label, colour, MOTION, carriage(x)))
        mates.append(seat(label, "rail"))
    tabled = n == 2 and rng.random() < 0.6
    if tabled:
        tl, tt = xs[1] - xs[0] + cl, _u(rng, 6, 15)
        parts.append(PartSpec("table", _pick(rng, ("zinc", "alu", "green")), NO_CATEGORY,
                              lambda: _box(tl, cw, tt, x=(xs[0] + xs[1]) / 2, z=rh + top_t)))
        mates += [seat("table", f"carriage-{k + 1}") for k in range(n)]
    fit_ = "loose" if loose else "fitted"
    return Design(f"rail {rl:g}x{rw:g}x{rh:g} {'on a ledge' if ledge else 'free'}, {n} {fit_} "
                  f"carriage(s) {cl:g}x{cw:g}" + (", table" if tabled else ""),
                  tuple(parts), tuple(mates))


# --------------------------------------------------------------------------- key and hub


def draw_keyed_hub(rng: np.random.Generator) -> Design:
    """A hub on a shaft, driven by a parallel key shorter than the shaft's closed keyway; the
    key touches the hub's slot ceiling (a fitted key) or keeps the standard clearance, and the
    hub rests on a shaft shoulder or not. Along X or upright."""
    d = _u(rng, 10, 43, 1.0)
    _, _, b, h, t1, t2 = next(k for k in _KEYS if k[0] <= d < k[1])
    tight = bool(rng.random() < 0.5)
    hub_depth = h - t1 if tight else t2
    hw = _u(rng, 1.2 * d, 2.5 * d, 1.0)
    od = _u(rng, 1.8 * d, 3 * d, 1.0)
    shoulder = bool(rng.random() < 0.5)
    near = _u(rng, 1.5 * d, 3 * d, 1.0)  # shaft length up to the hub's far face
    a = near + hw + (0.0 if shoulder else _u(rng, 5, 2 * d, 1.0))
    step = _u(rng, 4, 10)
    tail = _u(rng, d, 3 * d, 1.0)
    kl = hw - _u(rng, 2, hw / 4)
    k0 = near + (hw - kl) / 2
    key_l = kl - _u(rng, 1, max(1.0, kl / 4))
    key_z = k0 + _u(rng, 0.5, kl - key_l - 0.5)  # its ends free: it slides

    def shaft() -> bd.Shape[Any]:
        body = _shaft([(d, a), (d + step, tail)]) if shoulder else _shaft([(d, a + tail)])
        pocket = bd.Pos(0, d / 2 - t1, k0) * bd.Box(b, t1 + 1, kl, align=(
            bd.Align.CENTER, bd.Align.MIN, bd.Align.MIN))
        return _cut(body, pocket)

    def hub() -> bd.Shape[Any]:
        z = a - hw if shoulder else near
        slot = bd.Pos(0, 0, z - 1) * bd.Box(b, d / 2 + hub_depth, hw + 2, align=(
            bd.Align.CENTER, bd.Align.MIN, bd.Align.MIN))
        return _cut(_cyl(od / 2, hw, z=z), _cyl(d / 2, hw + 2, z=z - 1), slot)

    def key() -> bd.Shape[Any]:
        return bd.Pos(0, d / 2 - t1, key_z) * bd.Box(b, h, key_l, align=(
            bd.Align.CENTER, bd.Align.MIN, bd.Align.MIN))

    along_x = bool(rng.random() < 0.5)
    turn = TO_X if along_x else bd.Rot(0, 0, 0)
    parts = [PartSpec("shaft", "steel", MOTION, placed(turn, shaft)),
             PartSpec("hub", _pick(rng, BODY_COLOURS), MOTION, placed(turn, hub)),
             PartSpec("key", _pick(rng, ("dark", "brass")), FASTENERS, placed(turn, key))]
    mates: list[Mate] = [fit("hub", "shaft"), seat("key", "shaft"), seat("key", "hub")]
    if shoulder:
        mates.append(seat("hub", "shaft"))
    return Design(f"hub {od:g}x{hw:g} on a {d:g} mm shaft, key {b:g}x{h:g}x{key_l:g} "
                  f"({'fitted' if tight else 'standard'})"
                  + (", on a shoulder" if shoulder else ""), tuple(parts), tuple(mates))


# --------------------------------------------------------------------------- segmented ring


def _sector(ri: float, ro: float, h: float, a0: float, a1: float, z: float) -> bd.Solid:
    """The part of the ring ri..ro (height h from z) between the angles a0 < a1 (degrees)."""
    big = 4 * ro
    steps = max(2, math.ceil((a1 - a0) / 30))
    rim = [(big * math.cos(math.radians(a0 + (a1 - a0) * i / steps)),
            big * math.sin(math.radians(a0 + (a1 - a0) * i / steps))) for i in range(steps + 1)]
    wedge = bd.Pos(0, 0, z - 1) * bd.extrude(bd.Polygon((0, 0), *rim, align=None), h + 2)
    ring = _cut(_cyl(ro, h, z=z), _cyl(ri, h + 2, z=z - 1))
    common = ring.intersect(wedge)
    return _one(bd.Compound(common.solids() if common is not None else []), "ring segment")


def draw_segmented_ring(rng: np.random.Generator) -> Design:
    """A ring split into 2 to 8 segments that touch end to end (a split collar, a segmented
    cage or bushing) on a shaft, often inside a housing: neighbouring segments rest face to face
    on their radial cuts (planar) while each turns on the shaft (cylindrical, or revolute when
    the ring sits on a shaft shoulder)."""
    d = _u(rng, 10, 60, 1.0)
    wall, h = _u(rng, 2, max(3.0, 0.4 * d)), _u(rng, 4, max(6.0, 0.8 * d))
    n = int(_pick(rng, ("2", "3", "4", "6", "8")))
    start = _u(rng, 0, 360 / n, 1.0)
    shoulder, housed = bool(rng.random() < 0.4), bool(rng.random() < 0.5)
    near, tail, step = _u(rng, d, 3 * d, 1.0), _u(rng, 0.5 * d, 2 * d, 1.0), _u(rng, 2, 6)
    z0 = near - h if shoulder else near - h - _u(rng, 2, d, 1.0)
    ro = d / 2 + wall

    def shaft() -> bd.Shape[Any]:
        return _shaft([(d, near), (d + step, tail)]) if shoulder else _shaft([(d, near + tail)])

    turn = TO_X if rng.random() < 0.5 else bd.Rot(0, 0, 0)
    colour = _pick(rng, ("brass", "dark", "zinc", "red"))
    parts = [PartSpec("shaft", "steel", MOTION, placed(turn, shaft))]
    mates: list[Mate] = []
    for k in range(n):
        a0 = start + 360 * k / n
        label = f"segment-{k + 1}"
        parts.append(PartSpec(label, colour, MOTION, placed(
            turn, functools.partial(_sector, d / 2, ro, h, a0, a0 + 360 / n, z0))))
        mates.append(fit(label, "shaft"))
        if n > 2 or k == 0:  # two halves touch on both cuts: one pair
            mates.append(seat(label, f"segment-{(k + 1) % n + 1}"))
        if shoulder:
            mates.append(seat(label, "shaft"))
        if housed:
            mates.append(fit(label, "housing"))
    if housed:
        housing_r = _u(rng, ro + 4, ro + 3 * wall + 6)
        parts.append(PartSpec("housing", _pick(rng, BODY_COLOURS), NO_CATEGORY, placed(
            turn, lambda: _cut(_cyl(housing_r, h, z=z0), _cyl(ro, h + 2, z=z0 - 1)))))
    return Design(f"{n} segments {d:g}/{2 * ro:g}x{h:g} on a {d:g} mm shaft"
                  + (", on a shoulder" if shoulder else "") + (", housed" if housed else ""),
                  tuple(parts), tuple(mates))
