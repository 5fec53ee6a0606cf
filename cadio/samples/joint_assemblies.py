"""Assembly families of joints: bolted lap joints, casters and shaft couplings (sleeve, jaw,
flange). Each ``draw_*`` takes a seeded generator and returns a ``Design``.

Bolts pass through clearance holes whose wall is at most 0.75 mm from the shank (ISO 273 close
or normal holes, whichever stays within the concentric mate's 1 mm), sit on the stack with or
without a washer, and end in a nut that leaves two threads or more free. The couplings lie along
X, as the library's own do. Draws that would repeat a library assembly's parameters are drawn
again, so no variant is one of the library's five.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from typing import Any

import build123d as bd
import numpy as np

from cadio.samples.assembly_kit import (
    BRAKES,
    CASTERS,
    MOTION,
    NO_CATEGORY,
    SIZES,
    TO_X,
    Design,
    Mate,
    Metric,
    PartSpec,
    fastened,
    fit,
    metric,
    placed,
    seat,
)
from cadio.samples.parts import (
    _C75S,
    _box,
    _Caster,
    _caster_axle,
    _caster_fork,
    _caster_plate,
    _caster_wheel,
    _cut,
    _cyl,
    _flange_coupling,
    _jaw_hub,
    _jaw_spider,
    _polar,
    _shaft,
    _sleeve_coupling,
)
from cadio.samples.variants import _pick, _u

_PLATE_COLOURS = ("blue", "green", "iron", "alu", "orange", "steel")


def _hole(rng: np.random.Generator, m: Metric) -> float:
    """A clearance hole for ``m`` whose wall stays within 0.75 mm of the shank."""
    holes = [h for h in (m.hole_close, m.hole_normal) if (h - m.d) / 2 <= 0.75]
    return holes[int(rng.integers(len(holes)))]


def _along_x(parts: list[PartSpec]) -> tuple[PartSpec, ...]:
    """The parts turned so that the design's Z axis lies along X."""
    return tuple(replace(p, build=placed(TO_X, p.build)) for p in parts)


# --------------------------------------------------------------------------- bolted joint


def draw_bolted_joint(rng: np.random.Generator) -> Design:
    """Two lapped plates joined by a grid of 2 to 8 bolts, each with a nut and washers."""
    m = metric(_pick(rng, SIZES))
    socket, thin = bool(rng.random() < 0.3), bool(rng.random() < 0.3)
    head_washer, nut_washer = bool(rng.random() < 0.4), bool(rng.random() < 0.8)
    nx, ny = int(rng.integers(1, 5)), int(rng.integers(1, 3))
    nx = max(nx, 3 - ny)  # at least two bolts: the library's joint has one
    hole = _hole(rng, m)
    t1, t2 = (_u(rng, max(3.0, 0.5 * m.d), 2.5 * m.d) for _ in range(2))
    pitch_min = max(3 * m.d, 2 * m.footprint_r + 2)
    pitch = _u(rng, pitch_min, 1.8 * pitch_min, 1.0)
    edge_min = max(1.5 * m.d, m.footprint_r + 1)
    ex, ey = _u(rng, edge_min, 1.5 * edge_min), _u(rng, edge_min, 2 * edge_min)
    lap, width = (nx - 1) * pitch + 2 * ex, (ny - 1) * pitch + 2 * ey
    long1, long2 = lap + _u(rng, 20, 120, 1.0), lap + _u(rng, 20, 120, 1.0)
    spots = [(-lap / 2 + ex + i * pitch, -width / 2 + ey + j * pitch)
             for i in range(nx) for j in range(ny)]

    def drilled(plate: bd.Shape[Any]) -> bd.Solid:
        return _cut(plate, *[_cyl(hole / 2, t1 + t2 + 2, x, y, -1) for x, y in spots])

    lower = (lambda: drilled(_box(long1, width, t1, x=lap / 2 - long1 / 2)))
    upper = (lambda: drilled(_box(long2, width, t2, x=long2 / 2 - lap / 2, z=t1)))
    parts = [PartSpec("plate-lower", _pick(rng, _PLATE_COLOURS), NO_CATEGORY, lower),
             PartSpec("plate-upper", _pick(rng, _PLATE_COLOURS), NO_CATEGORY, upper)]
    mates = [seat("plate-lower", "plate-upper")]
    for k, (x, y) in enumerate(spots):
        more, found = fastened(str(k + 1), m, bd.Pos(x, y, t1 + t2), t1 + t2, socket=socket,
                               thin=thin, head_washer=head_washer, nut_washer=nut_washer,
                               top_part="plate-upper", bottom_part="plate-lower")
        parts += more
        mates += found
    kind = "cap screws" if socket else "bolts"
    return Design(f"lap joint {t1:g}+{t2:g} mm, {nx}x{ny} {m.size} {kind} in {hole:g} holes, "
                  f"pitch {pitch:g}", tuple(parts), tuple(mates))


# --------------------------------------------------------------------------- caster


def draw_caster(rng: np.random.Generator) -> Design:
    """Swivel or fixed caster: top plate, fork, headed axle, wheel (``parts._Caster``)."""
    c = _C75S
    while c == _C75S:  # the library's caster assembly
        d = _u(rng, 40, 125, 1.0)
        c = _Caster(wheel_d=d, wheel_w=_u(rng, 0.3 * d, 0.4 * d, 1.0),
                    axle_d=_u(rng, 6, 12, 1.0),
                    plate=_u(rng, max(50, 0.8 * d), 1.1 * d + 10, 1.0),
                    swivel=bool(rng.random() < 0.6), sheet=_u(rng, 2.5, 4),
                    race_h=_u(rng, 6, 10))
    builds: tuple[tuple[str, str, Callable[[_Caster], bd.Solid]], ...] = (
        ("plate", "zinc", _caster_plate), ("fork", _pick(rng, _PLATE_COLOURS), _caster_fork),
        ("axle", "dark", _caster_axle), ("wheel", _pick(rng, ("red", "dark", "orange")),
                                         _caster_wheel))
    parts = [PartSpec(label, colour, CASTERS, partial(build, c))
             for label, colour, build in builds]
    mates = [seat("plate", "fork"), fit("fork", "axle"), seat("fork", "axle"),
             fit("axle", "wheel"), seat("fork", "wheel")]
    kind = "swivel" if c.swivel else "fixed"
    return Design(f"{kind} caster wheel {c.wheel_d:g}x{c.wheel_w:g} axle {c.axle_d:g} "
                  f"plate {c.plate:g} sheet {c.sheet:g} race {c.race_h:g}", tuple(parts),
                  tuple(mates))


# --------------------------------------------------------------------------- couplings


def _shafts(d: float, a_top: float, a_len: float, b_bottom: float, b_len: float
            ) -> list[PartSpec]:
    """Shaft a ending at ``a_top`` from below, shaft b starting at ``b_bottom``, along Z."""
    return [PartSpec("shaft-a", "steel", MOTION,
                     placed(bd.Pos(0, 0, a_top - a_len), lambda: _shaft([(d, a_len)]))),
            PartSpec("shaft-b", "dark", MOTION,
                     placed(bd.Pos(0, 0, b_bottom), lambda: _shaft([(d, b_len)])))]


def draw_sleeve_coupling(rng: np.random.Generator) -> Design:
    """Rigid sleeve coupling on two shafts that butt in its middle or stop short of it."""
    bore, od, length = 10.0, 20.0, 30.0
    while (bore, od, length) == (10.0, 20.0, 30.0):  # the library's sleeve coupling
        bore = _u(rng, 6, 30, 1.0)
        od, length = bore + _u(rng, 8, 20, 1.0), max(20.0, _u(rng, 2.5 * bore, 4 * bore, 1.0))
    gap = 0.0 if rng.random() < 0.4 else _u(rng, 1, 4)
    mid = length / 2
    shafts = _shafts(bore, mid - gap / 2, _u(rng, length, 4 * length, 1.0), mid + gap / 2,
                     _u(rng, length, 4 * length, 1.0))
    parts = [PartSpec("sleeve", _pick(rng, ("brass", "steel", "iron")), BRAKES,
                      lambda: _sleeve_coupling(bore, od, length)), *shafts]
    mates = [fit("sleeve", "shaft-a"), fit("sleeve", "shaft-b")]
    if gap == 0.0:
        mates.append(seat("shaft-a", "shaft-b"))
    return Design(f"sleeve coupling {bore:g}x{od:g}x{length:g}, shafts {gap:g} mm apart",
                  _along_x(parts), tuple(mates))


def draw_jaw_coupling(rng: np.random.Generator) -> Design:
    """Jaw coupling: hub, elastomer spider between the jaws, hub turned by 60 degrees and
    flipped, a shaft in each hub."""
    od, bore, hub_l, jaw_h = 40.0, 14.0, 16.0, 12.0
    while (od, bore, hub_l, jaw_h) == (40.0, 14.0, 16.0, 12.0):  # the library's jaw coupling
        od = _u(rng, 25, 80, 1.0)
        bore, hub_l, jaw_h = _u(rng, 6, od / 3, 1.0), _u(rng, 10, 30, 1.0), _u(rng, 8, 18, 1.0)
    top = 2 * hub_l + jaw_h + 1
    parts = [PartSpec("hub-a", _pick(rng, ("alu", "iron")), BRAKES,
                      lambda: _jaw_hub(od, bore, hub_l, jaw_h)),
             PartSpec("spider", _pick(rng, ("orange", "red", "green")), BRAKES,
                      placed(bd.Pos(0, 0, hub_l + 1), lambda: _jaw_spider(od, jaw_h - 1))),
             PartSpec("hub-b", _pick(rng, ("alu", "blue")), BRAKES,
                      placed(bd.Pos(0, 0, top) * bd.Rot(180, 0, 0),
                             lambda: _jaw_hub(od, bore, hub_l, jaw_h, phase=60)))]
    depth_a, depth_b = _u(rng, hub_l / 2, hub_l - 1), _u(rng, hub_l / 2, hub_l - 1)
    parts += _shafts(bore, depth_a, _u(rng, 2 * hub_l, 6 * hub_l, 1.0), top - depth_b,
                     _u(rng, 2 * hub_l, 6 * hub_l, 1.0))
    mates = [fit("hub-a", "shaft-a"), fit("hub-b", "shaft-b"), seat("hub-a", "spider"),
             seat("spider", "hub-b"), fit("hub-a", "spider"), fit("spider", "hub-b")]
    return Design(f"jaw coupling {od:g} bore {bore:g} hub {hub_l:g} jaws {jaw_h:g}",
                  _along_x(parts), tuple(mates))


def _bolts_on_circle(pcd: float, footprint_r: float) -> int:
    """The most bolts on a circle of diameter ``pcd`` whose footprints keep 1 mm apart."""
    return int(math.pi / math.asin(min(1.0, (2 * footprint_r + 1) / pcd)))


def draw_flange_coupling(rng: np.random.Generator) -> Design:
    """Two rigid flange halves face to face, bolted on their bolt circle, a shaft in each."""
    m = metric(_pick(rng, SIZES))
    flange_d = 10 * _hole(rng, m)  # ``parts._flange_coupling`` drills flange_d / 10 holes
    hub_max = flange_d - 4 * (m.footprint_r + 0.5)
    hub_d = _u(rng, 0.6 * hub_max, hub_max, 1.0)
    bore = _u(rng, max(6.0, 0.3 * hub_d), hub_d / 1.6, 1.0)
    flange_t, hub_l = _u(rng, max(6.0, m.d), 2.5 * m.d), _u(rng, max(15.0, bore), 2.5 * bore, 1.0)
    pcd = (flange_d + hub_d) / 2
    n = int(rng.integers(3, max(3, min(8, _bolts_on_circle(pcd, m.footprint_r))) + 1))
    thin, washers = bool(rng.random() < 0.3), bool(rng.random() < 0.5)
    half = (lambda: _flange_coupling(bore, flange_d, flange_t, hub_d, hub_l, n))
    colour = _pick(rng, ("iron", "steel", "blue"))
    parts = [PartSpec("half-a", colour, BRAKES, placed(bd.Rot(180, 0, 0), half)),
             PartSpec("half-b", colour, BRAKES, half)]
    mates: list[Mate] = [seat("half-a", "half-b")]
    for k, (x, y, _) in enumerate(_polar(pcd / 2, n)):
        more, found = fastened(str(k + 1), m, bd.Pos(x, y, flange_t), 2 * flange_t,
                               socket=False, thin=thin, head_washer=False, nut_washer=washers,
                               top_part="half-b", bottom_part="half-a")
        parts += more
        mates += found
    reach = flange_t + hub_l
    parts += _shafts(bore, -_u(rng, 0.5, 3), _u(rng, reach, 3 * reach, 1.0), _u(rng, 0.5, 3),
                     _u(rng, reach, 3 * reach, 1.0))
    mates += [fit("half-a", "shaft-a"), fit("half-b", "shaft-b")]
    nuts = ("thin nuts" if thin else "nuts") + (" on washers" if washers else "")
    return Design(f"flange coupling {flange_d:g}x{flange_t:g} hub {hub_d:g}x{hub_l:g} bore "
                  f"{bore:g}, {n} {m.size} bolts, {nuts}", _along_x(parts), tuple(mates))
