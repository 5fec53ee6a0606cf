"""Geometry of the sample library's assemblies: named, coloured parts placed in contact.

Each assembly is a list of solids in file order, positioned so that parts touch (face, seat or
bore contact) without interfering and shaft lines are coaxial; the tests check both. Parts reuse
the single-part builders of ``cadio.samples.parts``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import build123d as bd
from bd_warehouse import bearing as bdw_bearing
from bd_warehouse import fastener as bdw_fastener

from cadio.samples.parts import (
    _C75S,
    _bearing,
    _box,
    _caster_axle,
    _caster_fork,
    _caster_plate,
    _caster_wheel,
    _cut,
    _cyl,
    _jaw_hub,
    _jaw_spider,
    _shaft,
    _sleeve_coupling,
    dress_solid,
)


def _hang(shape: bd.Shape[Any], top_z: float) -> bd.Shape[Any]:
    """``shape`` moved along Z so that its highest point is at ``top_z``."""
    moved: bd.Shape[Any] = bd.Pos(0, 0, top_z - shape.bounding_box().max.Z) * shape
    return moved


def _bolted_joint() -> list[bd.Solid]:
    """Lap joint: two 8 mm plates in face contact, M8 bolt down through a 9 mm hole,
    washer and nut stacked under the lower plate, all on the Z axis."""
    t, f = 8.0, bdw_fastener
    lower = _cut(_box(60, 40, t, x=-15), _cyl(4.5, t + 2, z=-1))
    upper = _cut(_box(60, 40, t, x=15, z=t), _cyl(4.5, t + 2, z=t - 1))
    bolt = bd.Pos(0, 0, 2 * t) * f.HexHeadScrew("M8-1.25", 30, "iso4017", simple=True)
    washer = _hang(f.PlainWasher("M8", "iso7089"), 0.0)
    nut = _hang(f.HexNut("M8-1.25", "iso4032", simple=True), washer.bounding_box().min.Z)
    parts = [(lower, "plate-lower", "blue"), (upper, "plate-upper", "green"),
             (bolt, "bolt", "dark"), (washer, "washer", "zinc"), (nut, "nut", "brass")]
    return [dress_solid(shape, label, colour) for shape, label, colour in parts]


def _bearing_housing() -> list[bd.Solid]:
    """608-2Z bearing seated on a 3 mm shoulder in a flange housing, on an 8 mm shaft."""
    h, corners = 10.0, [(x, y) for x in (-18, 18) for y in (-18, 18)]
    holes = [_cyl(2.75, h + 2, x, y, -1) for x, y in corners]
    housing = _cut(_box(50, 50, h), _cyl(11, 8, z=3), _cyl(8, h + 2, z=-1), *holes)
    brg = bd.Pos(0, 0, 3) * _bearing(bdw_bearing.SingleRowCappedDeepGrooveBallBearing, "M8-22-7")
    shaft = bd.Pos(0, 0, -20) * _shaft([(8, 60)])
    parts = [(housing, "housing", "blue"), (brg, "bearing", "steel"), (shaft, "shaft", "orange")]
    return [dress_solid(shape, label, colour) for shape, label, colour in parts]


def _caster_assembly() -> list[bd.Solid]:
    c = _C75S
    parts = [(_caster_plate(c), "plate", "zinc"), (_caster_fork(c), "fork", "blue"),
             (_caster_axle(c), "axle", "dark"), (_caster_wheel(c), "wheel", "red")]
    return [dress_solid(shape, label, colour) for shape, label, colour in parts]


def _sleeve_coupling_assembly() -> list[bd.Solid]:
    """Two 10 mm shafts along X meeting (2 mm apart) inside a rigid sleeve coupling."""
    to_x = bd.Rot(0, 90, 0)
    sleeve = to_x * bd.Pos(0, 0, -15) * _sleeve_coupling(10, 20, 30)
    shaft_a = to_x * bd.Pos(0, 0, -50) * _shaft([(10, 49)])
    shaft_b = to_x * bd.Pos(0, 0, 1) * _shaft([(10, 49)])
    parts = [(sleeve, "sleeve", "brass"), (shaft_a, "shaft-a", "steel"),
             (shaft_b, "shaft-b", "green")]
    return [dress_solid(shape, label, colour) for shape, label, colour in parts]


def _jaw_coupling_assembly() -> list[bd.Solid]:
    """Jaw coupling along X: hub, spider, hub turned by 60 degrees and flipped, two shafts."""
    to_x = bd.Rot(0, 90, 0)
    hub_a = _jaw_hub(40, 14, 16, 12)
    hub_b = bd.Pos(0, 0, 45) * bd.Rot(180, 0, 0) * _jaw_hub(40, 14, 16, 12, phase=60)
    spider = bd.Pos(0, 0, 17) * _jaw_spider(40, 11)
    shaft_a = bd.Pos(0, 0, -40) * _shaft([(14, 54)])
    shaft_b = bd.Pos(0, 0, 31) * _shaft([(14, 54)])
    parts = [(hub_a, "hub-a", "alu"), (spider, "spider", "orange"), (hub_b, "hub-b", "blue"),
             (shaft_a, "shaft-a", "steel"), (shaft_b, "shaft-b", "dark")]
    return [dress_solid(to_x * shape, label, colour) for shape, label, colour in parts]


def assembly_builders() -> list[tuple[str, str, Callable[[], list[bd.Solid]]]]:
    """(name, description, build) of each assembly; ``build`` returns its parts in order."""
    return [
        ("bolted-joint-m8", "M8 bolt, washer and nut through two lapped plates", _bolted_joint),
        ("bearing-housing-608", "608-2Z ball bearing in a flange housing on a shaft",
         _bearing_housing),
        ("swivel-caster-d75", "Swivel caster 75 mm: plate, fork, axle, wheel", _caster_assembly),
        ("sleeve-coupling-d10", "Rigid sleeve coupling joining two 10 mm shafts",
         _sleeve_coupling_assembly),
        ("jaw-coupling-d40", "Jaw coupling with spider joining two 14 mm shafts",
         _jaw_coupling_assembly),
    ]
