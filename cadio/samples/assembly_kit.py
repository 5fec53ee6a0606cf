"""Pieces shared by the assembly variant families: the design record, fasteners, stud shafts.

A family's draw returns a ``Design``: its parts (label, colour, paper category and a builder
that returns the part already placed in the assembly frame, millimetres, Z up) and the face
mates the layout is built to have (``Mate``: a shaft in a bore, a washer on a plate). Nothing is
built at draw time.

Fasteners come from bd_warehouse, whose simplified screws are cylinders at the thread's minor
diameter: an M8 shank in a 9 mm hole would then sit 1.2 mm off the hole wall, beyond the 1 mm
of a concentric mate, where a vendor's bolt (modelled at its nominal diameter) sits 0.5 mm off.
``bolt`` therefore fuses a nominal-diameter shank over the thread (the last millimetre stays at
the minor diameter, a thread run-out chamfer). Sizes and heights for layouts are read from
bd_warehouse's own tables, so the layout and the built part cannot disagree.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import build123d as bd
from bd_warehouse import fastener as bdw_fastener

from cadio.records import Category, Relation
from cadio.samples.parts import _cyl, _fuse, _shaft

COINCIDENT, CONCENTRIC = Relation.COINCIDENT.value, Relation.CONCENTRIC.value
FIT, CLEARANCE = "fit", "clearance"
FASTENERS, MOTION = Category.FASTENERS.value, Category.MOTION.value
BRAKES, CASTERS = Category.BRAKES.value, Category.CASTERS.value
NO_CATEGORY = ""  # plates and frames: parts of no paper category
BODY_COLOURS = ("blue", "green", "iron", "alu", "orange")  # housings, bases, hubs
TO_X = bd.Rot(0, 90, 0)  # turns +Z into +X


@dataclass(frozen=True)
class Mate:
    """A face mate a variant is built to have between the parts labelled ``a`` and ``b``.

    relation: "coincident" (planar faces face to face) or "concentric" (coaxial cylinders
    within 1 mm); fit: for concentric, "fit" (same radius) or "clearance".
    """

    a: str
    b: str
    relation: str
    fit: str | None = None


@dataclass(frozen=True)
class PartSpec:
    """One part of a design: label (the STEP product name), colour (a ``parts._COLOURS``
    key), paper category ("" for none) and a builder of the part placed in the assembly."""

    label: str
    colour: str
    category: str
    build: Callable[[], bd.Shape[Any]]


@dataclass(frozen=True)
class Design:
    """A drawn assembly: its description (the drawn parameters), parts in file order, and the
    face mates it is built to have."""

    description: str
    parts: tuple[PartSpec, ...]
    mates: tuple[Mate, ...]


def fit(a: str, b: str) -> Mate:
    """A shaft in a bore of its own diameter."""
    return Mate(a, b, CONCENTRIC, FIT)


def clearance(a: str, b: str) -> Mate:
    """A shaft in a larger bore, within the 1 mm of a concentric mate."""
    return Mate(a, b, CONCENTRIC, CLEARANCE)


def seat(a: str, b: str) -> Mate:
    """Planar faces of a and b face to face."""
    return Mate(a, b, COINCIDENT)


def placed(where: bd.Location, build: Callable[[], bd.Shape[Any]]) -> Callable[[], bd.Shape[Any]]:
    """A builder of ``build()`` moved by ``where``."""

    def moved() -> bd.Shape[Any]:
        shape: bd.Shape[Any] = where * build()
        return shape

    return moved


# --------------------------------------------------------------------------- fasteners

SIZES = ("M4-0.7", "M5-0.8", "M6-1", "M8-1.25", "M10-1.5", "M12-1.75")


@dataclass(frozen=True)
class Metric:
    """Dimensions (mm) of one metric size, from bd_warehouse's tables.

    d: nominal diameter; nut_m / thin_m: ISO 4032 / 4035 nut height; nut_e: the larger nut's
    width across corners; washer_id, washer_od, washer_h: ISO 7089 washer; hex_e: ISO 4017
    head width across corners; cap_dk: ISO 4762 head diameter; hole_close, hole_normal:
    clearance hole diameters.
    """

    size: str
    d: float
    nut_m: float
    thin_m: float
    nut_e: float
    washer_id: float
    washer_od: float
    washer_h: float
    hex_e: float
    cap_dk: float
    hole_close: float
    hole_normal: float

    @property
    def head_r(self) -> float:
        """Radius of the larger head (hex across corners or cap screw)."""
        return max(self.hex_e, self.cap_dk) / 2

    @property
    def footprint_r(self) -> float:
        """Radius a bolt's head, nut or washer needs around its axis."""
        return max(self.head_r, self.nut_e / 2, self.washer_od / 2)


@functools.cache
def _table(name: str) -> dict[str, dict[str, str]]:
    table: dict[str, dict[str, str]] = bdw_fastener.read_fastener_parameters_from_csv(name)
    return {key: {k.strip(): v for k, v in row.items()} for key, row in table.items()}


@functools.cache
def metric(size: str) -> Metric:
    """Dimensions of ``size`` (one of ``SIZES``, e.g. "M8-1.25")."""
    short = size.split("-")[0]
    nut, washer = _table("hex_nut_parameters.csv")[size], _table("plain_washer_parameters.csv")
    hex_s = float(_table("hex_head_parameters.csv")[size]["iso4017:s"])
    hole = _table("clearance_hole_sizes.csv")[short]
    corners = 2 / 3**0.5  # across corners / across flats of a hexagon
    return Metric(
        size=size, d=float(short[1:]), nut_m=float(nut["iso4032:m"]),
        thin_m=float(nut["iso4035:m"]),
        nut_e=corners * max(float(nut["iso4032:s"]), float(nut["iso4035:s"])),
        washer_id=float(washer[short]["iso7089:d1"]), washer_od=float(washer[short]["iso7089:d2"]),
        washer_h=float(washer[short]["iso7089:h"]), hex_e=corners * hex_s,
        cap_dk=float(_table("socket_head_cap_parameters.csv")[size]["iso4762:dk"]),
        hole_close=float(hole["Close"]), hole_normal=float(hole["Normal"]))


def bolt(size: str, length: float, socket: bool = False) -> bd.Solid:
    """Hex head bolt (ISO 4017) or socket head cap screw (ISO 4762) with a nominal-diameter
    shank: the head's bearing face at z = 0, the shank down to z = -length."""
    f = bdw_fastener
    screw = (f.SocketHeadCapScrew(size, length, "iso4762", simple=True) if socket
             else f.HexHeadScrew(size, length, "iso4017", simple=True))
    return _fuse(screw, _cyl(metric(size).d / 2, length - 1.0, z=-length + 1.0))


def nut(size: str, thin: bool = False) -> bd.Solid:
    """ISO 4032 (or thin ISO 4035) hex nut from z = 0 up."""
    solid: bd.Solid = bdw_fastener.HexNut(size, "iso4035" if thin else "iso4032", simple=True)
    return solid


def washer(size: str) -> bd.Solid:
    """ISO 7089 plain washer from z = 0 up."""
    solid: bd.Solid = bdw_fastener.PlainWasher(size.split("-")[0], "iso7089")
    return solid


def nut_height(m: Metric, thin: bool) -> float:
    return m.thin_m if thin else m.nut_m


def bolt_length(grip: float, m: Metric, thin: bool) -> float:
    """Whole millimetres: through ``grip`` and the nut, with two threads' worth sticking out."""
    return float(int(grip + nut_height(m, thin) + 0.25 * m.d + 2.0) + 1)


# A design's choices, each a keyword: the call reads as the joint's description.
def fastened(name: str, m: Metric, top: bd.Location, grip: float, *,  # noqa: PLR0913
             socket: bool, thin: bool, head_washer: bool, nut_washer: bool, top_part: str,
             bottom_part: str) -> tuple[list[PartSpec], list[Mate]]:
    """A bolt down through a stack of ``grip`` mm whose top face is at ``top`` (local z = 0,
    the axis local Z), with optional washers under the head and the nut, and its nut.

    ``top_part`` and ``bottom_part`` are the labels of the parts whose faces the stack's top
    and bottom are (the same label for a single part). Parts are named ``<kind>-<name>``.
    """
    tag = f"-{name}" if name else ""
    labels = {k: f"{k}{tag}" for k in ("bolt", "washer-head", "washer", "nut")}
    hw, nw = (m.washer_h if head_washer else 0.0), (m.washer_h if nut_washer else 0.0)
    length = bolt_length(grip + hw + nw, m, thin)
    b, parts = labels["bolt"], []
    parts.append(PartSpec(b, "dark" if socket else "zinc", FASTENERS,
                          placed(top * bd.Pos(0, 0, hw), lambda: bolt(m.size, length, socket))))
    mates = [clearance(top_part, b), clearance(bottom_part, b)]
    if head_washer:
        parts.append(PartSpec(labels["washer-head"], "zinc", FASTENERS,
                              placed(top, lambda: washer(m.size))))
        mates += [seat(b, labels["washer-head"]), seat(labels["washer-head"], top_part),
                  clearance(labels["washer-head"], b)]
    else:
        mates.append(seat(b, top_part))
    under = bottom_part
    if nut_washer:
        parts.append(PartSpec(labels["washer"], "zinc", FASTENERS,
                              placed(top * bd.Pos(0, 0, -grip - nw), lambda: washer(m.size))))
        mates += [seat(labels["washer"], bottom_part), clearance(labels["washer"], b)]
        under = labels["washer"]
    low = top * bd.Pos(0, 0, -grip - nw - nut_height(m, thin))
    parts.append(PartSpec(labels["nut"], "brass" if thin else "zinc", FASTENERS,
                          placed(low, lambda: nut(m.size, thin))))
    mates += [seat(labels["nut"], under), fit(labels["nut"], b)]
    return parts, mates


# --------------------------------------------------------------------------- shafts


def stud_shaft(d: float, socket_l: float, shoulder_d: float, shoulder_l: float,
               top_l: float) -> bd.Solid:
    """A stud along +Z: ``socket_l`` of diameter d below z = 0 (into a plate), a shoulder of
    ``shoulder_d`` on z in [0, shoulder_l] (resting on the plate), then ``top_l`` of d."""
    stud: bd.Solid = bd.Pos(0, 0, -socket_l) * _shaft(
        [(d, socket_l), (shoulder_d, shoulder_l), (d, top_l)])
    return stud
