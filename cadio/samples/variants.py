"""Parametric variants of the sample part families, for training the learned stages.

Sixty sample parts are too few to train a shape-completion network. Each family of
``cadio.samples.parts`` (bolts, nuts, washers, shafts, bearings, pulleys, gears, couplings, brake
discs and drums, wheels, casters, ...) is drawn here again with other sizes, proportions and
feature counts, from a seeded random generator: the same seed and count give the same parts,
byte for byte. Draws stay inside ranges where the builders make one valid solid; a draw that
still fails is left out (and logged), so the count per category is an upper bound.

A variant's name carries its family and index (``wheel-v0007``); its description the drawn
parameters. Variants are never the library's own sixty parts (other parameters), so a model
trained on variants has never seen the sample library.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import build123d as bd
import numpy as np
from bd_warehouse import fastener as bdw_fastener

from cadio.records import Category
from cadio.samples import parts as p

Draw = Callable[[np.random.Generator], tuple[str, Callable[[], bd.Shape[Any]]]]

_THREADS = ("M3-0.5", "M4-0.7", "M5-0.8", "M6-1", "M8-1.25", "M10-1.5", "M12-1.75", "M16-2")
_WASHERS = ("M3", "M4", "M5", "M6", "M8", "M10", "M12", "M16")


@dataclass(frozen=True)
class Variant:
    """One drawn part: category folder, unique name, description (its parameters), builder."""

    category: str
    name: str
    description: str
    build: Callable[[], bd.Shape[Any]]


def _u(rng: np.random.Generator, lo: float, hi: float, step: float = 0.5) -> float:
    """A uniform draw in [lo, hi] rounded to ``step`` (readable names, exact STEP bytes)."""
    return float(round(rng.uniform(lo, hi) / step) * step)


def _pick(rng: np.random.Generator, items: tuple[str, ...]) -> str:
    return str(items[int(rng.integers(len(items)))])


# --------------------------------------------------------------------------- fasteners


def _screw(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    f = bdw_fastener
    kind = int(rng.integers(4))
    size = _pick(rng, _THREADS[:6] if kind == 3 else _THREADS)
    d = float(size[1:].split("-")[0])
    length = _u(rng, 2.0 * d, 6.0 * d, 1.0)
    builds: tuple[tuple[str, Callable[[], bd.Shape[Any]]], ...] = (
        ("hex bolt", lambda: f.HexHeadScrew(size, length, "iso4017", simple=True)),
        ("socket cap screw", lambda: f.SocketHeadCapScrew(size, length, "iso4762", simple=True)),
        ("countersunk screw", lambda: f.CounterSunkScrew(size, length, "iso10642", simple=True)),
        ("button head screw", lambda: f.ButtonHeadScrew(size, length, "iso7380_1", simple=True)))
    label, build = builds[kind]
    return f"{label} {size}x{length:g}", build


def _nut(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    f, size, u = bdw_fastener, _pick(rng, _THREADS), rng.random()
    if u < 0.4:
        return f"hex nut {size}", lambda: f.HexNut(size, "iso4032", simple=True)
    if u < 0.7:
        return f"thin hex nut {size}", lambda: f.HexNut(size, "iso4035", simple=True)
    return f"domed cap nut {size}", lambda: f.DomedCapNut(size, "din1587", simple=True)


def _washer(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    size = _pick(rng, _WASHERS)
    if rng.random() < 0.6:
        return f"plain washer {size}", lambda: bdw_fastener.PlainWasher(size, "iso7089")
    return f"large washer {size}", lambda: bdw_fastener.PlainWasher(size, "iso7093")


def _set_screw(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    size = _pick(rng, _THREADS[1:6])
    d = float(size[1:].split("-")[0])
    length = _u(rng, 1.5 * d, 3.0 * d, 1.0)
    return (f"set screw {size}x{length:g}",
            lambda: bdw_fastener.SetScrew(size, length, "iso4026", simple=True))


# --------------------------------------------------------------------------- motion


def _stepped_shaft(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    n = int(rng.integers(1, 5))
    base = _u(rng, 8, 30, 1.0)
    segments = [(max(4.0, base + _u(rng, -6, 8, 1.0)), _u(rng, 10, 60, 1.0)) for _ in range(n)]
    text = "/".join(f"{d:g}x{length:g}" for d, length in segments)
    return f"stepped shaft {text}", lambda: p._shaft(segments)


def _keyed(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    d = _u(rng, 10, 30, 1.0)
    length = _u(rng, 3 * d, 8 * d, 1.0)
    key_w = max(2.0, round(d / 4))
    return (f"keyed shaft {d:g}x{length:g}",
            lambda: p._keyed_shaft(d, length, key_w, key_w * 0.6))


def _bearing(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    bore = _u(rng, 6, 40, 1.0)
    od = bore + _u(rng, 8, 40, 1.0)
    width = _u(rng, 0.25 * od, 0.45 * od, 0.5)
    return (f"sealed bearing {bore:g}x{od:g}x{width:g}",
            lambda: p._sealed_bearing(bore, od, width))


def _pulley(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    od = _u(rng, 60, 160, 1.0)
    bore = _u(rng, 8, min(30, od / 2 - 22), 1.0)
    return f"v-belt pulley {od:g} bore {bore:g}", lambda: p._v_pulley(od, bore)


def _gear(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    module = _pick(rng, ("1", "1.25", "1.5", "2", "2.5"))
    teeth = int(rng.integers(14, 40))
    width = _u(rng, 6, 20, 1.0)
    bore = _u(rng, 5, max(6.0, float(module) * teeth / 3), 1.0)
    return (f"spur gear m{module} z{teeth} w{width:g} bore {bore:g}",
            lambda: p._spur_gear(float(module), teeth, width, bore))


def _collar(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    bore = _u(rng, 6, 30, 1.0)
    od = bore + _u(rng, 8, 20, 1.0)
    width = _u(rng, 7, 16, 1.0)
    return f"shaft collar {bore:g}x{od:g}x{width:g}", lambda: p._shaft_collar(bore, od, width)


def _rail(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    length = _u(rng, 90, 360, 10.0)
    return f"linear rail 15x{length:g}", lambda: p._linear_rail(length)


# --------------------------------------------------------------------------- brakes, couplings


def _flange(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    bore = _u(rng, 12, 40, 1.0)
    hub = bore * _u(rng, 1.8, 2.4, 0.1)
    flange = hub * _u(rng, 2.0, 2.8, 0.1)
    t = _u(rng, 10, 22, 1.0)
    hub_l = _u(rng, 25, 60, 1.0)
    bolts = int(rng.integers(3, 9))
    return (f"flange coupling bore {bore:g} flange {flange:g} {bolts} bolts",
            lambda: p._flange_coupling(bore, flange, t, hub, hub_l, bolts))


def _jaw(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    od = _u(rng, 25, 60, 1.0)
    bore = _u(rng, 6, od / 3, 1.0)
    if rng.random() < 0.3:
        t = _u(rng, 8, 14, 1.0)
        return f"jaw spider {od:g}x{t:g}", lambda: p._jaw_spider(od, t)
    hub_l, jaw_h = _u(rng, 10, 25, 1.0), _u(rng, 7, 15, 1.0)
    return (f"jaw hub {od:g} bore {bore:g}", lambda: p._jaw_hub(od, bore, hub_l, jaw_h))


def _sleeve(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    bore = _u(rng, 8, 30, 1.0)
    od = bore + _u(rng, 8, 20, 1.0)
    length = _u(rng, 2.5 * bore, 4 * bore, 1.0)
    return f"sleeve coupling {bore:g}x{od:g}x{length:g}", lambda: p._sleeve_coupling(
        bore, od, length)


def _disc(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    od = _u(rng, 180, 320, 5.0)
    kind = int(rng.integers(3))
    if kind == 0:
        ring_w, t = od * _u(rng, 0.15, 0.25, 0.01), _u(rng, 8, 14, 1.0)
        hat, bore = _u(rng, 30, 55, 1.0), _u(rng, 50, 70, 1.0)
        return (f"brake disc solid {od:g}", lambda: p._brake_disc(od, ring_w, t, hat, bore))
    if kind == 1:
        return f"brake disc drilled {od:g}", lambda: p._drilled_disc(od)
    return f"brake disc vented {od:g}", lambda: p._vented_disc(od)


def _clutch_or_drum(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    if rng.random() < 0.5:
        od = _u(rng, 150, 260, 5.0)
        return f"clutch plate {od:g}", lambda: p._clutch_plate(od)
    od = _u(rng, 140, 260, 5.0)
    return f"brake drum {od:g}", lambda: p._brake_drum(od)


# --------------------------------------------------------------------------- casters, wheels


def _wheel(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    d = _u(rng, 40, 160, 1.0)
    w = _u(rng, 0.25 * d, 0.45 * d, 1.0)
    bore = _u(rng, 6, min(20, d / 5), 1.0)
    holes = int(rng.choice([0, 0, 4, 5, 6, 8])) if d >= 70 else 0
    return f"wheel {d:g}x{w:g} bore {bore:g} holes {holes}", lambda: p._wheel(d, w, bore, holes)


def _caster_part(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    d = _u(rng, 40, 125, 1.0)
    c = p._Caster(wheel_d=d, wheel_w=_u(rng, 0.3 * d, 0.4 * d, 1.0),
                  axle_d=_u(rng, 6, 12, 1.0), plate=_u(rng, max(50, 0.8 * d), 1.1 * d + 10, 1.0),
                  swivel=bool(rng.random() < 0.6))
    kinds: tuple[tuple[str, Callable[[p._Caster], bd.Solid]], ...] = (
        ("caster", p._caster), ("caster plate", p._caster_plate), ("caster fork", p._caster_fork),
        ("caster axle", p._caster_axle))
    label, build = kinds[int(rng.integers(len(kinds)))]
    kind = "swivel" if c.swivel else "fixed"
    return f"{label} {kind} wheel {d:g}", lambda: build(c)


def _handle(rng: np.random.Generator) -> tuple[str, Callable[[], bd.Shape[Any]]]:
    width, height, bar = _u(rng, 120, 400, 5.0), _u(rng, 200, 700, 10.0), _u(rng, 14, 30, 1.0)
    return (f"trolley handle {width:g}x{height:g} bar {bar:g}",
            lambda: p._trolley_handle(width, height, bar))


FAMILIES: dict[str, tuple[tuple[str, Draw, str], ...]] = {
    Category.FASTENERS.value: (("screw", _screw, "zinc"), ("nut", _nut, "zinc"),
                               ("washer", _washer, "zinc"), ("set-screw", _set_screw, "dark")),
    Category.MOTION.value: (("shaft", _stepped_shaft, "steel"), ("keyed-shaft", _keyed, "steel"),
                            ("bearing", _bearing, "steel"), ("pulley", _pulley, "alu"),
                            ("gear", _gear, "brass"), ("collar", _collar, "dark"),
                            ("rail", _rail, "steel")),
    Category.BRAKES.value: (("flange-coupling", _flange, "iron"), ("jaw", _jaw, "orange"),
                            ("sleeve", _sleeve, "steel"), ("disc", _disc, "iron"),
                            ("clutch-drum", _clutch_or_drum, "iron")),
    Category.CASTERS.value: (("wheel", _wheel, "red"), ("caster", _caster_part, "blue"),
                             ("handle", _handle, "dark")),
}


def draw_variants(per_category: int, seed: int = 0) -> list[Variant]:
    """``per_category`` variants of each paper category, families taken in turn.

    Args:
        per_category: variants drawn per category (0 for none).
        seed: the generator's seed; draws depend only on (seed, category, index).

    Returns:
        Variants in (category, index) order; nothing is built yet.
    """
    out = []
    for c, (category, families) in enumerate(FAMILIES.items()):
        for i in range(per_category):
            family, draw, colour = families[i % len(families)]
            rng = np.random.default_rng([seed, c, i])
            description, build = draw(rng)
            name = f"{family}-v{i:04d}"
            out.append(Variant(category, name, description,
                               _dressed(build, name, colour)))
    return out


def _dressed(build: Callable[[], bd.Shape[Any]], name: str,
             colour: str) -> Callable[[], bd.Shape[Any]]:
    return lambda: p.dress_solid(build(), name, colour)
