"""Assembly families built around shafts: bearings in a housing, open ball bearings, pillow
blocks, gear and pulley pairs on studs. Each ``draw_*`` takes a seeded generator and returns a
``Design``.

Layouts follow the fits of real machines: a bearing's outer ring sits in a bore of its own
diameter on a shoulder, the shaft in its inner ring; collars sit on the shaft against the inner
ring only (never the housing); a stud's shoulder rests on its plate with its socket in a bore of
its own diameter; gears mesh at their nominal centre distance plus a working backlash (their
teeth are drawn without any, so flanks would touch on both sides). Every contact is exact
(faces on one plane or one cylinder); every other gap is at least half a millimetre, but for
the backlash between meshing teeth (0.07-0.16 mm measured).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import build123d as bd
import numpy as np

from cadio.samples.assembly_kit import (
    BODY_COLOURS,
    FASTENERS,
    MOTION,
    NO_CATEGORY,
    SIZES,
    TO_X,
    Design,
    Mate,
    Metric,
    PartSpec,
    bolt,
    clearance,
    fit,
    metric,
    placed,
    seat,
    stud_shaft,
)
from cadio.samples.parts import (
    _Z0,
    _box,
    _cut,
    _cyl,
    _fuse,
    _sealed_bearing,
    _shaft,
    _shaft_collar,
    _spur_gear,
    _v_pulley,
)
from cadio.samples.variants import _pick, _u

Build = Callable[[], bd.Shape[Any]]
_BACKLASH_MM = 0.1  # centre distance beyond nominal, plus 5% of the module


@dataclass(frozen=True)
class _Bearing:
    """A sealed bearing's radii (see ``parts._sealed_bearing``): bore, inner ring's outer edge,
    outer ring's inner edge, outside; and the radius of a housing's through hole behind its
    shoulder (between the rings, so that only the outer ring bears on the shoulder)."""

    d: float
    od: float
    width: float

    @property
    def inner_ring(self) -> float:
        return self.d / 2 + 0.18 * (self.od - self.d)

    @property
    def outer_ring(self) -> float:
        return self.od / 2 - 0.18 * (self.od - self.d)

    @property
    def through(self) -> float:
        return (self.inner_ring + self.outer_ring) / 2

    def build(self) -> bd.Solid:
        return _sealed_bearing(self.d, self.od, self.width)


def _draw_bearing(rng: np.random.Generator, d_lo: float, d_hi: float) -> _Bearing:
    d = _u(rng, d_lo, d_hi, 1.0)
    od = d + _u(rng, 10, 30, 1.0)
    return _Bearing(d, od, _u(rng, max(5.0, 0.25 * od), 0.45 * od, 0.5))


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'s' if n > 1 else ''}"


def _collar_od(rng: np.random.Generator, b: _Bearing | _BallBearing, limit: float) -> float:
    """A collar bearing on the inner ring only and staying inside radius ``limit``."""
    return float(math.floor(2 * (b.inner_ring + _u(rng, 0.0, 0.7, 0.1)
                                 * (limit - b.inner_ring))))


# --------------------------------------------------------------------------- bearings on a shaft


def _housing(b: _Bearing | _BallBearing, two: bool, lip: float, wall: float,
             square: bool) -> bd.Solid:
    """Housing along Z from z = 0: a bearing seat of the bearing's width above a lip (or a seat
    at each end of a middle web), a through hole behind, four corner holes when square."""
    height = b.width * (2 if two else 1) + lip
    side = b.od + 2 * wall
    body = _box(side, side, height) if square else _cyl(side / 2, height)
    seats = [_cyl(b.od / 2, b.width + 1, z=height - b.width)]
    if two:
        seats.append(_cyl(b.od / 2, b.width + 1, z=-1))
    q = side / 2 - wall / 2
    holes = ([_cyl(wall * 0.3, height + 2, x, y, -1) for x in (-q, q) for y in (-q, q)]
             if square else [])
    return _cut(body, *seats, _cyl(b.through, height + 2, z=-1), *holes)


def draw_bearing_shaft(rng: np.random.Generator) -> Design:
    """One or two sealed bearings in a housing on a shaft, with one or two collars."""
    b = _draw_bearing(rng, 6, 30)
    two, square = bool(rng.random() < 0.5), bool(rng.random() < 0.6)
    lip, wall = _u(rng, 2, 5), _u(rng, 5, 15, 1.0)
    n_collars, cw = int(rng.integers(1, 3)), _u(rng, 5, 12, 1.0)
    height = b.width * (2 if two else 1) + lip
    names = ["bearing-a", "bearing-b"] if two else ["bearing"]
    centres = [b.width / 2, height - b.width / 2] if two else [height - b.width / 2]
    # collars: above the top bearing (outside), then below the lowest one (inside the through
    # hole of a single housing, outside a double one)
    co = _collar_od(rng, b, b.through - 0.5)
    collar_z = [height, (0.0 if two else lip) - cw][:n_collars]
    collar_on = [names[-1], names[0]]
    low = min([0.0, *collar_z]) - _u(rng, 3, 25, 1.0)
    length = height + cw + _u(rng, 3, 25, 1.0) - low
    colour = _pick(rng, BODY_COLOURS)
    parts = [PartSpec("housing", colour, MOTION,
                      lambda: _housing(b, two, lip, wall, square)),
             *[PartSpec(n, "steel", MOTION, placed(bd.Pos(0, 0, z), b.build))
               for n, z in zip(names, centres, strict=True)],
             PartSpec("shaft", "orange", MOTION,
                      placed(bd.Pos(0, 0, low), lambda: _shaft([(b.d, length)])))]
    mates = [m for n in names for m in (fit(n, "shaft"), fit(n, "housing"), seat(n, "housing"))]
    for k, z in enumerate(collar_z):
        label = f"collar-{'ab'[k]}"
        parts.append(PartSpec(label, "dark", MOTION,
                              placed(bd.Pos(0, 0, z), lambda: _shaft_collar(b.d, co, cw))))
        mates += [fit(label, "shaft"), seat(label, collar_on[k])]
    kind = "square" if square else "round"
    return Design(f"{_count(len(names), 'bearing')} {b.d:g}x{b.od:g}x{b.width:g} in a {kind} "
                  f"housing, {_count(n_collars, 'collar')} {co:g}x{cw:g}", tuple(parts),
                  tuple(mates))


# --------------------------------------------------------------------------- open ball bearings
# Rings, balls and a shaft as separate parts, the way vendors' bearing assemblies come: balls touch
# the rings' grooves at a point (sphere in a torus, no face mate), the rings share an axis without
# touching (no mate), and only the bore, the outside and the shoulder make mates.

# Bearing sizes of bd_warehouse's deep groove table (d, D, B, d1, D1: bore, outside, width, inner
# ring's and outer ring's shoulder diameters), read there so that the layout cannot disagree.
_BALL_SIZES = ("M5-16-5", "M6-19-6", "M7-22-7", "M8-22-7", "M8-24-8", "M9-24-7", "M9-26-8",
               "M10-26-8", "M10-28-8", "M10-30-9", "M10-35-11")
_CONFORMITY = 0.52  # groove radius over ball diameter (deep groove bearings: 0.515-0.53)


@dataclass(frozen=True)
class _BallBearing:
    """An open deep groove ball bearing on the Z axis, centred on z = 0: ``n`` balls of
    diameter ``ball`` on the pitch circle between rings whose shoulders are at ``inner_ring``
    and ``outer_ring`` (radii); the rings' grooves conform to the ball (``_CONFORMITY``)."""

    d: float
    od: float
    width: float
    inner_ring: float
    outer_ring: float
    ball: float
    n: int

    @property
    def pitch(self) -> float:
        return (self.inner_ring + self.outer_ring) / 2

    @property
    def through(self) -> float:  # a housing's hole behind its shoulder, between the rings
        return self.pitch

    def _groove(self, sign: int) -> bd.Shape[Any]:
        """The torus whose tube touches the ball at its innermost (sign -1) or outermost
        (+1) point."""
        rg, rb = _CONFORMITY * self.ball, self.ball / 2
        return bd.Torus(self.pitch - sign * (rg - rb), rg)

    def inner(self) -> bd.Solid:
        ring = bd.Pos(0, 0, -self.width / 2) * bd.Cylinder(
            self.inner_ring, self.width, align=_Z0) - _cyl(self.d / 2, self.width + 2,
                                                          z=-self.width / 2 - 1)
        return _cut(ring, self._groove(-1))

    def outer(self) -> bd.Solid:
        ring = bd.Pos(0, 0, -self.width / 2) * bd.Cylinder(
            self.od / 2, self.width, align=_Z0) - _cyl(self.outer_ring, self.width + 2,
                                                       z=-self.width / 2 - 1)
        return _cut(ring, self._groove(1))

    def ball_at(self, k: int) -> Build:
        angle = 2 * math.pi * k / self.n
        where = bd.Pos(self.pitch * math.cos(angle), self.pitch * math.sin(angle), 0)
        return lambda: where * bd.Solid.make_sphere(self.ball / 2)


def _draw_ball_bearing(rng: np.random.Generator) -> _BallBearing:
    from bd_warehouse.bearing import SingleRowDeepGrooveBallBearing

    size = _BALL_SIZES[int(rng.integers(len(_BALL_SIZES)))]
    table = SingleRowDeepGrooveBallBearing.bearing_data[size]
    d, od, width, d1, big_d1 = (float(table[f"SKT:{k}"]) for k in ("d", "D", "B", "d1", "D1"))
    ball = round((big_d1 - d1) * _u(rng, 0.58, 0.66, 0.01), 3)
    pitch = (d1 + big_d1) / 4
    # as many balls as the pitch circle holds with at least 0.5 mm between neighbours
    most = int(math.pi / math.asin(min(1.0, (ball + 0.5) / (2 * pitch))))
    n = int(rng.integers(max(5, most - 3), most + 1))
    return _BallBearing(d, od, width, d1 / 2, big_d1 / 2, ball, n)


def draw_ball_bearing(rng: np.random.Generator) -> Design:
    """An open ball bearing (rings and balls apart) on a shaft, in a housing (half of them: the
    balls of the others are in sight, as on a bench), with a collar on the inner ring (always
    where there is no housing)."""
    b = _draw_ball_bearing(rng)
    housed, square = bool(rng.random() < 0.5), bool(rng.random() < 0.5)
    lip, wall = _u(rng, 2, 5), _u(rng, 5, 12, 1.0)
    height = b.width + lip
    centre = height - b.width / 2
    collar, cw = bool(rng.random() < 0.5) or not housed, _u(rng, 4, 10, 1.0)
    co = _collar_od(rng, b, b.pitch - b.ball / 2 - 0.5)  # clear of the balls
    low = -_u(rng, 3, 20, 1.0)
    length = height + (cw if collar else 0.0) + _u(rng, 3, 20, 1.0) - low
    body = _pick(rng, BODY_COLOURS)
    parts = [PartSpec("outer-ring", "steel", MOTION, placed(bd.Pos(0, 0, centre), b.outer)),
             PartSpec("inner-ring", "steel", MOTION, placed(bd.Pos(0, 0, centre), b.inner)),
             *[PartSpec(f"ball-{k + 1:02d}", "steel", MOTION,
                        placed(bd.Pos(0, 0, centre), b.ball_at(k))) for k in range(b.n)],
             PartSpec("shaft", "orange", MOTION,
                      placed(bd.Pos(0, 0, low), lambda: _shaft([(b.d, length)])))]
    mates = [fit("inner-ring", "shaft")]
    if housed:
        parts.insert(0, PartSpec("housing", body, MOTION,
                                 lambda: _housing(b, False, lip, wall, square)))
        mates += [fit("outer-ring", "housing"), seat("outer-ring", "housing")]
    if collar:
        parts.append(PartSpec("collar", "dark", MOTION,
                              placed(bd.Pos(0, 0, height), lambda: _shaft_collar(b.d, co, cw))))
        mates += [fit("collar", "shaft"), seat("collar", "inner-ring")]
    where = f"in a {'square' if square else 'round'} housing" if housed else "without housing"
    return Design(f"open ball bearing {b.d:g}x{b.od:g}x{b.width:g} with {b.n} balls of "
                  f"{b.ball:g} {where}, {'a collar' if collar else 'no collar'}"
                  f"{f' {co:g}x{cw:g}' if collar else ''}", tuple(parts), tuple(mates))


# --------------------------------------------------------------------------- pillow blocks


@dataclass(frozen=True)
class _Block:
    """Pillow block with its shaft along +X: inner face at x = 0, bearing seat open towards -X
    on a lip, foot on z = 0, axis at height ``axis_z``; foot holes at ``hole_y`` (if any)."""

    b: _Bearing
    lip: float
    wall: float
    foot_t: float
    axis_z: float
    pad: float
    foot_x: float
    hole_d: float

    @property
    def thick(self) -> float:
        return self.b.width + self.lip

    @property
    def boss_r(self) -> float:
        return self.b.od / 2 + self.wall

    @property
    def hole_y(self) -> float:
        return self.boss_r + self.pad / 2

    def build(self) -> bd.Solid:
        t, r, z = self.thick, self.boss_r, self.axis_z
        foot = _box(self.foot_x, 2 * (r + self.pad), self.foot_t, x=t / 2)
        pedestal = _box(t, 2 * r - 2 * min(2.0, self.wall / 3), z, x=t / 2)
        boss = bd.Pos(0, 0, z) * TO_X * bd.Cylinder(r, t, align=_Z0)
        seat_bore = bd.Pos(-1, 0, z) * TO_X * bd.Cylinder(self.b.od / 2, self.b.width + 1,
                                                            align=_Z0)
        through = bd.Pos(-1, 0, z) * TO_X * bd.Cylinder(self.b.through, t + 2, align=_Z0)
        holes = ([_cyl(self.hole_d / 2, self.foot_t + 2, t / 2, s * self.hole_y, -1)
                  for s in (-1, 1)] if self.hole_d else [])
        return _cut(_fuse(foot, pedestal, boss), seat_bore, through, *holes)


def draw_pillow_blocks(rng: np.random.Generator) -> Design:
    """Two pillow blocks with sealed bearings on a base plate, a shaft through both, a collar
    inside each; the blocks screwed to the plate (cap screws in tapped holes) or not."""
    b = _draw_bearing(rng, 8, 30)
    wall, lip, foot_t = _u(rng, 5, 12, 1.0), _u(rng, 2, 4), _u(rng, 6, 15)
    m = metric(_pick(rng, SIZES[:5])) if rng.random() < 0.7 else None
    pad = _u(rng, 2 * m.head_r + 3, 2 * m.head_r + 10) if m else _u(rng, 5, 15)
    foot_x = max(b.width + lip, 2 * m.head_r + 4) if m else b.width + lip
    block = _Block(b, lip, wall, foot_t, b.od / 2 + wall + foot_t + _u(rng, 0, 8), pad,
                   foot_x, m.hole_normal if m else 0.0)
    g, cw = _u(rng, 20, 100, 1.0), _u(rng, 5, 12, 1.0)
    co = _collar_od(rng, b, b.through)
    reach = g + block.thick / 2 + foot_x / 2
    size_x, size_y = 2 * (reach + _u(rng, 5, 30, 1.0)), 2 * (block.hole_y + pad / 2
                                                           + _u(rng, 5, 30, 1.0))
    plate_t = _u(rng, max(8.0, 1.5 * m.d + 2 if m else 8.0), 20)
    ends = (g + block.thick + _u(rng, 5, 40, 1.0), g + block.thick + _u(rng, 5, 40, 1.0))
    screws = [(s * (g + block.thick / 2), y) for s in (1, -1)
              for y in (-block.hole_y, block.hole_y)] if m else []
    tap_d = m.d if m else 0.0

    def base() -> bd.Shape[Any]:
        plate = _box(size_x, size_y, plate_t, z=-plate_t)
        taps = [_cyl(tap_d / 2, plate_t + 2, x, y, -plate_t - 1) for x, y in screws]
        return _cut(plate, *taps) if taps else plate

    parts = [PartSpec("base", _pick(rng, BODY_COLOURS), NO_CATEGORY, base),
             PartSpec("shaft", "steel", MOTION,
                      placed(bd.Pos(-ends[1], 0, block.axis_z) * TO_X,
                             lambda: _shaft([(b.d, sum(ends))])))]
    mates: list[Mate] = []
    colour = _pick(rng, BODY_COLOURS)
    for s, k in ((1, "a"), (-1, "b")):
        turn = bd.Pos(s * g, 0, 0) * bd.Rot(0, 0, 0 if s > 0 else 180)
        brg, blk, col = f"bearing-{k}", f"block-{k}", f"collar-{k}"
        on_axis = bd.Pos(s * g, 0, block.axis_z)
        collar_at = on_axis * bd.Pos(-cw if s > 0 else 0, 0, 0) * TO_X
        parts += [PartSpec(blk, colour, MOTION, placed(turn, block.build)),
                  PartSpec(brg, "steel", MOTION,
                           placed(on_axis * bd.Pos(s * b.width / 2, 0, 0) * TO_X, b.build)),
                  PartSpec(col, "dark", MOTION,
                           placed(collar_at, lambda: _shaft_collar(b.d, co, cw)))]
        mates += [seat(blk, "base"), fit(brg, blk), seat(brg, blk), fit(brg, "shaft"),
                  fit(col, "shaft"), seat(col, brg)]
    if m:
        more, found = _foot_screws(m, screws, foot_t)
        parts += more
        mates += found
    screwed = f", {m.size.split('-')[0]} screws" if m else ""
    return Design(f"pillow blocks {b.d:g}x{b.od:g}x{b.width:g} {2 * g:g} apart{screwed}",
                  tuple(parts), tuple(mates))


def _foot_screws(m: Metric, spots: list[tuple[float, float]], foot_t: float
                 ) -> tuple[list[PartSpec], list[Mate]]:
    """Cap screws down through the feet (two per block, block a first) into tapped holes of
    the base plate, 1.5 diameters deep."""
    length = float(int(foot_t + 1.5 * m.d))
    parts, mates = [], []
    for i, (x, y) in enumerate(spots):
        label, block = f"screw-{i + 1}", f"block-{'aabb'[i]}"
        parts.append(PartSpec(label, "dark", FASTENERS,
                              placed(bd.Pos(x, y, foot_t),
                                     lambda: bolt(m.size, length, socket=True))))
        mates += [seat(label, block), clearance(block, label), fit("base", label)]
    return parts, mates


# --------------------------------------------------------------------------- wheels on studs


@dataclass(frozen=True)
class _Wheel:
    """A gear or pulley on a stud at (x, 0): bore d, from z = 0 to ``width`` about +Z; the
    stud's shoulder and the collar stay inside ``hub_r`` (the face they bear on)."""

    label: str
    x: float
    d: float
    width: float
    hub_r: float
    colour: str
    build: Build


def _studs(rng: np.random.Generator, wheels: list[_Wheel], reach: float) -> Design:
    """Each wheel on its own stud: the stud's socket in a bore of a base plate, its shoulder on
    the plate, the wheel on the shoulder, a collar on the wheel; ``reach`` is the wheels'
    largest radius (the plate's margin starts there)."""
    plate_t, shoulder_l, cw = _u(rng, 6, 16), _u(rng, 2, 6), _u(rng, 5, 10, 1.0)
    xs = [w.x for w in wheels]
    margin = reach + _u(rng, 5, 25, 1.0)
    size_x, size_y = max(xs) - min(xs) + 2 * margin, 2 * margin
    centre_x = (max(xs) + min(xs)) / 2

    def base() -> bd.Solid:
        sockets = [_cyl(w.d / 2, plate_t + 2, w.x, 0, -plate_t - 1) for w in wheels]
        return _cut(_box(size_x, size_y, plate_t, x=centre_x, z=-plate_t), *sockets)

    parts = [PartSpec("base", _pick(rng, BODY_COLOURS), NO_CATEGORY, base)]
    mates: list[Mate] = []
    for k, w in enumerate(wheels):
        tag = "ab"[k]
        shoulder_d = min(w.d + _u(rng, 4, 8, 1.0), 2 * w.hub_r - 2)
        co = min(w.d + _u(rng, 6, 16, 1.0), 2 * w.hub_r - 2)
        top_l = w.width + cw + _u(rng, 0, 10, 1.0)
        stud, collar = f"stud-{tag}", f"collar-{tag}"
        parts += [PartSpec(stud, "steel", MOTION,
                           placed(bd.Pos(w.x, 0, 0), partial(stud_shaft, w.d, plate_t, shoulder_d,
                                                             shoulder_l, top_l))),
                  PartSpec(w.label, w.colour, MOTION,
                           placed(bd.Pos(w.x, 0, shoulder_l), w.build)),
                  PartSpec(collar, "dark", MOTION,
                           placed(bd.Pos(w.x, 0, shoulder_l + w.width),
                                  partial(_shaft_collar, w.d, co, cw)))]
        mates += [fit("base", stud), seat(stud, "base"), fit(w.label, stud), seat(w.label, stud),
                  fit(collar, stud), seat(collar, w.label)]
    return Design("", tuple(parts), tuple(mates))


def draw_gear_pair(rng: np.random.Generator) -> Design:
    """Two spur gears meshing at their centre distance (plus a working backlash: the teeth
    are drawn without any, so flanks would touch on both sides), each on a stud in a plate."""
    module = float(_pick(rng, ("1", "1.25", "1.5", "2", "2.5", "3")))
    z_min = max(17, math.ceil((16 + 2.5 * module) / module))  # 17: no undercut at 20 degrees
    z1 = int(rng.integers(z_min, z_min + 14))
    z2 = int(rng.integers(z1, z1 + 24))
    centre = module * (z1 + z2) / 2 + _BACKLASH_MM + 0.05 * module
    wheels = []
    # the pinion has a tooth on +X; the wheel is turned to face it with a tooth space
    for k, (z, phase) in enumerate(((z1, 0.0), (z2, 180.0 - 180.0 / z2))):
        root = module * z / 2 - 1.25 * module
        d = _u(rng, 6, min(25.0, 2 * root - 10), 1.0)
        width = _u(rng, 6, 20, 1.0)
        build = placed(bd.Rot(0, 0, phase), partial(_spur_gear, module, z, width, d))
        wheels.append(_Wheel(f"gear-{'ab'[k]}", k * centre, d, width, root, "brass", build))
    design = _studs(rng, wheels, module * z2 / 2 + module)
    description = (f"spur gears m{module:g} z{z1}/z{z2} at {centre:g} mm, "
                   f"studs {wheels[0].d:g}/{wheels[1].d:g}")
    return Design(description, design.parts, design.mates)


def draw_pulley_drive(rng: np.random.Generator) -> Design:
    """One or two V-belt pulleys, each on a stud in a base plate (the belt left out)."""
    n = 1 if rng.random() < 0.25 else 2
    ods = [_u(rng, 50, 160, 1.0) for _ in range(n)]
    centre = (ods[0] + ods[-1]) / 2 + _u(rng, 5, 80, 1.0) if n == 2 else 0.0
    wheels = []
    for k, od in enumerate(ods):
        d = _u(rng, 6, min(30.0, od - 44), 1.0)
        turn = _u(rng, 0, 350, 10.0)
        build = placed(bd.Pos(0, 0, 10) * bd.Rot(0, 0, turn), partial(_v_pulley, od, d))
        wheels.append(_Wheel(f"pulley-{'ab'[k]}", k * centre, d, 20.0, d / 2 + 7, "alu", build))
    design = _studs(rng, wheels, max(ods) / 2)
    sizes = ", ".join(f"{od:g} bore {w.d:g}" for od, w in zip(ods, wheels, strict=True))
    apart = f", {centre:g} mm apart" if n == 2 else ""
    return Design(f"{_count(n, 'v-belt pulley')} {sizes}{apart}", design.parts, design.mates)
