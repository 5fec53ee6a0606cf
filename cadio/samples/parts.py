"""Geometry of the sample library's single parts, in the four paper categories.

Each ``*_builders`` function lists (name, description, build) for one category; ``build``
returns a shape in millimetres, Z up, that ``dress_solid`` checks is one valid solid and labels.
Nothing is built until a builder is called. The underscore helpers (primitives and the parts
that assemblies reuse) are shared with ``cadio.samples.assemblies`` only. Any change to geometry,
names or colours must bump ``cadio.samples.library.LIBRARY_VERSION``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import build123d as bd
from bd_warehouse import bearing as bdw_bearing
from bd_warehouse import fastener as bdw_fastener
from bd_warehouse import gear as bdw_gear

from cadio.errors import GeometryError

Builder = Callable[[], bd.Shape[Any]]
_Z0 = (bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN)  # centred in x, y; starting at z = 0

# --------------------------------------------------------------------------- colours

_COLOURS: dict[str, tuple[float, float, float]] = {
    "steel": (0.62, 0.64, 0.67), "dark": (0.22, 0.22, 0.25), "zinc": (0.80, 0.80, 0.74),
    "brass": (0.80, 0.62, 0.22), "red": (0.80, 0.18, 0.12), "blue": (0.15, 0.32, 0.72),
    "green": (0.20, 0.58, 0.30), "iron": (0.36, 0.36, 0.40), "orange": (0.92, 0.50, 0.10),
    "alu": (0.82, 0.84, 0.88),
}


def dress_solid(shape: bd.Shape[Any], label: str, colour: str) -> bd.Solid:
    """The single valid solid of ``shape``, labelled and coloured (a ``_COLOURS`` key).

    Raises:
        GeometryError: ``shape`` is not exactly one valid solid with volume.
    """
    solid = _one(shape, label)
    solid.label = label
    solid.color = bd.Color(*_COLOURS[colour])
    return solid


# --------------------------------------------------------------------------- primitives


def _one(shape: bd.Shape[Any], what: str = "sample") -> bd.Solid:
    """The single valid solid of ``shape``; GeometryError otherwise."""
    solids = shape.solids()
    if len(solids) != 1:
        raise GeometryError(what, f"expected one solid, got {len(solids)}")
    if not solids[0].is_valid or solids[0].volume <= 0:
        raise GeometryError(what, "the solid is invalid or has no volume")
    return solids[0]


def _cut(base: bd.Shape[Any], *tools: bd.Shape[Any]) -> bd.Solid:
    return _one(base.cut(*tools))


def _fuse(base: bd.Shape[Any], *others: bd.Shape[Any]) -> bd.Solid:
    return _one(base.fuse(*others).clean())


def _cyl(r: float, h: float, x: float = 0, y: float = 0, z: float = 0) -> bd.Shape[Any]:
    """Cylinder along +Z from (x, y, z)."""
    return bd.Pos(x, y, z) * bd.Cylinder(r, h, align=_Z0)


def _box(sx: float, sy: float, sz: float, x: float = 0, y: float = 0,
         z: float = 0) -> bd.Shape[Any]:
    """Box centred on (x, y) in plan, from z upwards."""
    return bd.Pos(x, y, z) * bd.Box(sx, sy, sz, align=_Z0)


def _revolved(profile: Sequence[tuple[float, float]]) -> bd.Solid:
    """Revolve a closed polygon given as (radius, z) points about the Z axis."""
    wire = bd.Wire.make_polygon([bd.Vector(r, 0, z) for r, z in profile], close=True)
    return _one(bd.revolve(bd.Face(wire), bd.Axis.Z))


def _polar(r: float, n: int, phase: float = 0.0) -> list[tuple[float, float, float]]:
    """n points (x, y, angle in degrees) evenly spaced on a circle of radius r."""
    angles = [phase + 360.0 * i / n for i in range(n)]
    return [(r * math.cos(math.radians(a)), r * math.sin(math.radians(a)), a) for a in angles]


def _bolt_holes(pcd: float, n: int, d: float, z: float, h: float) -> list[bd.Shape[Any]]:
    return [_cyl(d / 2, h, x, y, z) for x, y, _ in _polar(pcd / 2, n)]


def _radial_hole(d: float, z: float, length: float) -> bd.Shape[Any]:
    """A hole along +Y from the Z axis, at height z (set-screw and grease holes)."""
    return bd.Pos(0, length / 2, z) * bd.Rot(90, 0, 0) * bd.Cylinder(d / 2, length)


def _sector(r_in: float, r_out: float, mid_deg: float, span_deg: float, z: float,
            h: float) -> bd.Solid:
    """Annular sector about Z, bounded by two radial planes (jaws and spider arms)."""
    reach = 2.0 * r_out / math.cos(math.radians(span_deg / 2))
    a0, a1 = math.radians(mid_deg - span_deg / 2), math.radians(mid_deg + span_deg / 2)
    tri = [bd.Vector(0, 0, z), bd.Vector(reach * math.cos(a0), reach * math.sin(a0), z),
           bd.Vector(reach * math.cos(a1), reach * math.sin(a1), z)]
    wedge = bd.extrude(bd.Face(bd.Wire.make_polygon(tri, close=True)), amount=h)
    ring = _cut(_cyl(r_out, h, z=z), _cyl(r_in, h, z=z))
    return _one(bd.Compound(list(ring.intersect(wedge) or [])))


# --------------------------------------------------------------------------- fasteners


def fastener_builders() -> list[tuple[str, str, Builder]]:
    """Screws, bolts, nuts and washers from bd_warehouse (simplified threads)."""
    f = bdw_fastener
    return [
        ("hex-bolt-m6x20", "ISO 4017 hex head bolt M6x20",
         lambda: f.HexHeadScrew("M6-1", 20, "iso4017", simple=True)),
        ("hex-bolt-m8x30", "ISO 4017 hex head bolt M8x30",
         lambda: f.HexHeadScrew("M8-1.25", 30, "iso4017", simple=True)),
        ("hex-bolt-m10x45", "ISO 4014 hex head bolt M10x45, partly threaded",
         lambda: f.HexHeadScrew("M10-1.5", 45, "iso4014", simple=True)),
        ("hex-bolt-m12x60", "ISO 4014 hex head bolt M12x60, partly threaded",
         lambda: f.HexHeadScrew("M12-1.75", 60, "iso4014", simple=True)),
        ("socket-cap-screw-m4x12", "ISO 4762 socket head cap screw M4x12",
         lambda: f.SocketHeadCapScrew("M4-0.7", 12, "iso4762", simple=True)),
        ("socket-cap-screw-m5x20", "ISO 4762 socket head cap screw M5x20",
         lambda: f.SocketHeadCapScrew("M5-0.8", 20, "iso4762", simple=True)),
        ("socket-cap-screw-m8x25", "ISO 4762 socket head cap screw M8x25",
         lambda: f.SocketHeadCapScrew("M8-1.25", 25, "iso4762", simple=True)),
        ("countersunk-screw-m6x16", "ISO 10642 countersunk socket screw M6x16",
         lambda: f.CounterSunkScrew("M6-1", 16, "iso10642", simple=True)),
        ("button-head-screw-m5x10", "ISO 7380 button head screw M5x10",
         lambda: f.ButtonHeadScrew("M5-0.8", 10, "iso7380_1", simple=True)),
        ("set-screw-m6x10", "ISO 4026 flat point set screw M6x10",
         lambda: f.SetScrew("M6-1", 10, "iso4026", simple=True)),
        ("hex-nut-m6", "ISO 4032 hex nut M6", lambda: f.HexNut("M6-1", "iso4032", simple=True)),
        ("hex-nut-m8", "ISO 4032 hex nut M8",
         lambda: f.HexNut("M8-1.25", "iso4032", simple=True)),
        ("thin-hex-nut-m12", "ISO 4035 thin hex nut M12",
         lambda: f.HexNut("M12-1.75", "iso4035", simple=True)),
        ("domed-cap-nut-m8", "DIN 1587 domed cap nut M8",
         lambda: f.DomedCapNut("M8-1.25", "din1587", simple=True)),
        ("plain-washer-m6", "ISO 7089 plain washer M6", lambda: f.PlainWasher("M6", "iso7089")),
        ("plain-washer-m8", "ISO 7089 plain washer M8", lambda: f.PlainWasher("M8", "iso7089")),
        ("large-washer-m10", "ISO 7093 large plain washer M10",
         lambda: f.PlainWasher("M10", "iso7093")),
    ]


# --------------------------------------------------------------------------- motion


def _bearing(kind: type, size: str) -> bd.Solid:
    """A bd_warehouse bearing fused into one solid. Only shielded and roller bearings: fused
    open ball bearings (sphere-torus seams) do not read back from STEP as valid solids."""
    solids = kind(size, "SKT").solids()
    return _fuse(solids[0], *solids[1:])


def _sealed_bearing(bore: float, od: float, width: float) -> bd.Solid:
    """Sealed (2RS) bearing as seen from outside: two rings, seals recessed 0.4 mm."""
    rb, ro, h, c = bore / 2, od / 2, width / 2, min(1.0, width / 10)
    ri, rs, s = rb + (od - bore) * 0.18, ro - (od - bore) * 0.18, h - 0.4
    return _revolved([(rb + c, -h), (ri, -h), (ri, -s), (rs, -s), (rs, -h), (ro - c, -h),
                      (ro, -h + c), (ro, h - c), (ro - c, h), (rs, h), (rs, s), (ri, s),
                      (ri, h), (rb + c, h), (rb, h - c), (rb, -h + c)])


def _spur_gear(module: float, teeth: int, width: float, bore: float) -> bd.Solid:
    gear = bdw_gear.SpurGear(module, teeth, 20, width, align=_Z0)
    return _cut(gear, _cyl(bore / 2, width + 2, z=-1))


def _shaft(segments: Sequence[tuple[float, float]], chamfer: float = 0.5) -> bd.Solid:
    """Shaft along +Z from z = 0 made of (diameter, length) segments, chamfered ends."""
    c, pts = chamfer, [(0.0, 0.0), (segments[0][0] / 2 - chamfer, 0.0)]
    z = 0.0
    for i, (d, length) in enumerate(segments):
        pts.append((d / 2, z + (c if i == 0 else 0.0)))
        z += length
        pts.append((d / 2, z - (c if i == len(segments) - 1 else 0.0)))
    return _revolved([*pts, (segments[-1][0] / 2 - c, z), (0.0, z)])


def _keyed_shaft(d: float, length: float, key_w: float, key_depth: float) -> bd.Solid:
    key = bd.Pos(0, d / 2, length / 2 - length / 6) * bd.Box(key_w, 2 * key_depth, length / 2)
    return _cut(_shaft([(d, length)]), key)


def _v_pulley(od: float, bore: float) -> bd.Solid:
    r = od / 2
    profile = [(bore / 2, -10), (bore / 2 + 7, -10), (bore / 2 + 7, -3), (r - 14, -3),
               (r - 14, -10), (r, -10), (r, -5), (r - 9, -2), (r - 9, 2), (r, 5), (r, 10),
               (r - 14, 10), (r - 14, 3), (bore / 2 + 7, 3), (bore / 2 + 7, 10), (bore / 2, 10)]
    return _cut(_revolved(profile), _radial_hole(5, -7, r))


def _linear_rail(length: float) -> bd.Solid:
    rail = _box(length, 15, 12.5)
    grooves = [_box(length + 2, 4, 3, y=s * 7.5, z=6.5) for s in (-1, 1)]
    holes = []
    for x in range(-int(length / 2) + 30, int(length / 2), 60):
        holes += [_cyl(2.25, 14, x=x, z=-1), _cyl(3.75, 5.3, x=x, z=12.5 - 5.3)]
    return _cut(rail, *grooves, *holes)


def _linear_bushing() -> bd.Solid:
    profile = [(4, -12), (7.5, -12), (7.5, -9.3), (6.8, -9.3), (6.8, -8.2), (7.5, -8.2),
               (7.5, 8.2), (6.8, 8.2), (6.8, 9.3), (7.5, 9.3), (7.5, 12), (4, 12)]
    return _revolved(profile)


def _lead_screw_nut() -> bd.Solid:
    body = _revolved([(4, 0), (11, 0), (11, 3.5), (5.1, 3.5), (5.1, 15), (4, 15)])
    return _cut(body, *_bolt_holes(16, 4, 3.4, -1, 6))


def _shaft_collar(bore: float, od: float, width: float) -> bd.Solid:
    ring = _revolved([(bore / 2, 0), (od / 2, 0), (od / 2, width), (bore / 2, width)])
    return _cut(ring, _radial_hole(3.3, width / 2, od))


def motion_builders(gears: bool = True) -> list[tuple[str, str, Builder]]:
    """Bearings, shafts, pulleys, linear guides; the two spur gears only if ``gears``."""
    b = bdw_bearing
    parts: list[tuple[str, str, Builder]] = [
        ("shielded-bearing-608-2z", "Shielded deep groove ball bearing 8x22x7",
         lambda: _bearing(b.SingleRowCappedDeepGrooveBallBearing, "M8-22-7")),
        ("shielded-bearing-625-2z", "Shielded deep groove ball bearing 5x16x5",
         lambda: _bearing(b.SingleRowCappedDeepGrooveBallBearing, "M5-16-5")),
        ("shielded-bearing-688-2z", "Shielded thin section ball bearing 8x16x5",
         lambda: _bearing(b.SingleRowCappedDeepGrooveBallBearing, "M8-16-5")),
        ("sealed-bearing-6001-2rs", "Sealed deep groove ball bearing 12x28x8",
         lambda: _sealed_bearing(12, 28, 8)),
        ("sealed-bearing-6204-2rs", "Sealed deep groove ball bearing 20x47x14",
         lambda: _sealed_bearing(20, 47, 14)),
        ("roller-bearing-nu204", "Cylindrical roller bearing 20x47x14",
         lambda: _bearing(b.SingleRowCylindricalRollerBearing, "M20-47-14")),
        ("shaft-plain-d10x100", "Plain ground shaft 10 mm x 100 mm", lambda: _shaft([(10, 100)])),
        ("shaft-stepped-d20", "Stepped shaft 15/20/25/20 mm",
         lambda: _shaft([(15, 25), (20, 30), (25, 15), (20, 40)])),
        ("shaft-keyed-d16x80", "Shaft 16 mm x 80 mm with a 5 mm keyway",
         lambda: _keyed_shaft(16, 80, 5, 3)),
        ("v-belt-pulley-d80", "Single groove V-belt pulley 80 mm, bore 14 mm",
         lambda: _v_pulley(80, 14)),
        ("linear-rail-15x180", "Profile linear guide rail 15 mm x 180 mm",
         lambda: _linear_rail(180)),
        ("linear-bushing-lm8uu", "Linear ball bushing 8x15x24 with ring grooves",
         _linear_bushing),
        ("lead-screw-nut-t8", "Flanged lead screw nut T8", _lead_screw_nut),
        ("shaft-collar-d12", "Shaft collar 12 mm with set screw hole",
         lambda: _shaft_collar(12, 22, 9)),
    ]
    if gears:
        parts += [
            ("spur-gear-m2-z20", "Spur gear module 2, 20 teeth, bore 8 mm",
             lambda: _spur_gear(2, 20, 10, 8)),
            ("spur-gear-m1.5-z36", "Spur gear module 1.5, 36 teeth, bore 10 mm",
             lambda: _spur_gear(1.5, 36, 8, 10)),
        ]
    return parts


# --------------------------------------------------------------------------- brakes, couplings


def _flange_coupling(bore: float, flange_d: float, flange_t: float, hub_d: float,
                     hub_l: float, n_bolts: int) -> bd.Solid:
    """Coupling half: flange at z in [0, flange_t], hub above, keyed bore, bolt circle."""
    top = flange_t + hub_l
    body = _revolved([(bore / 2, 0), (flange_d / 2, 0), (flange_d / 2, flange_t),
                      (hub_d / 2, flange_t), (hub_d / 2, top), (bore / 2, top)])
    pcd = (flange_d + hub_d) / 2
    key = bd.Pos(0, bore / 2, -1) * bd.Box(bore / 4, bore / 4, top + 2, align=_Z0)
    return _cut(body, key, *_bolt_holes(pcd, n_bolts, flange_d / 10, -1, flange_t + 2))


def _jaw_hub(od: float, bore: float, hub_l: float, jaw_h: float, phase: float = 0) -> bd.Solid:
    """Jaw coupling hub along +Z: body [0, hub_l], three 40-degree jaws above it."""
    jaws = [_sector(od / 4, od / 2, phase + 120 * i, 40, hub_l - 0.5, jaw_h + 0.5)
            for i in range(3)]
    return _cut(_fuse(_cyl(od / 2, hub_l), *jaws), _cyl(bore / 2, hub_l + jaw_h + 2, z=-1))


def _jaw_spider(od: float, thickness: float) -> bd.Solid:
    """Elastomer spider: six 20-degree arms between the jaws, on a central ring."""
    ring = _cut(_cyl(od / 4, thickness), _cyl(od / 4 - 2, thickness))
    arms = [_sector(od / 4 - 0.5, od / 2, 30 + 60 * i, 20, 0, thickness) for i in range(6)]
    return _fuse(ring, *arms)


def _sleeve_coupling(bore: float, od: float, length: float) -> bd.Solid:
    tube = _revolved([(bore / 2, 0), (od / 2, 0), (od / 2, length), (bore / 2, length)])
    holes = [_radial_hole(bore / 2.5, z, od) for z in (length / 4, 3 * length / 4)]
    return _cut(tube, *holes)


def _brake_disc(od: float, ring_w: float, t: float, hat_h: float, bore: float) -> bd.Solid:
    """Hat-type brake disc: friction ring at z in [0, t], hat rising to hat_h, 5 studs."""
    r_in, wall, top = od / 2 - ring_w, 5.0, 7.0
    disc = _revolved([(bore / 2, hat_h - top), (r_in - wall, hat_h - top), (r_in - wall, 0),
                      (od / 2, 0), (od / 2, t), (r_in, t), (r_in, hat_h), (bore / 2, hat_h)])
    studs = _bolt_holes(bore + (r_in - wall - bore / 2), 5, 12.5, hat_h - top - 1, top + 2)
    return _cut(disc, *studs)


def _drilled_disc(od: float) -> bd.Solid:
    ring_w = od * 0.2
    disc = _brake_disc(od, ring_w, 12, 45, 60)
    radii = [od / 2 - ring_w * f for f in (0.25, 0.5, 0.75)]
    holes = [_cyl(3, 14, x, y, -1) for k, r in enumerate(radii)
             for x, y, _ in _polar(r, 12, phase=10.0 * k)]
    return _cut(disc, *holes)


def _vented_disc(od: float) -> bd.Solid:
    """Thick disc with 24 radial cooling channels between two 8 mm friction plates."""
    ring_w = od * 0.2
    disc = _brake_disc(od, ring_w, 24, 50, 64)
    r_mid = od / 2 - ring_w / 2 + 3
    vents = [bd.Pos(x, y, 8) * bd.Rot(0, 0, a) * bd.Box(ring_w, 5, 8, align=_Z0)
             for x, y, a in _polar(r_mid, 24)]
    return _cut(disc, *vents)


def _clutch_plate(od: float) -> bd.Solid:
    """Clutch friction disc: facings both sides, thin carrier, splined hub, damper windows."""
    r = od / 2
    disc = _revolved([(11, -8), (24, -8), (24, -0.75), (r - 30, -0.75), (r - 30, -3.5),
                      (r, -3.5), (r, 3.5), (r - 30, 3.5), (r - 30, 0.75), (24, 0.75), (24, 8),
                      (11, 8)])
    splines = [bd.Pos(x, y, -9) * bd.Rot(0, 0, a) * bd.Box(4, 3, 18, align=_Z0)
               for x, y, a in _polar(12, 10)]
    windows = [bd.Pos(x, y, -1) * bd.Rot(0, 0, a + 90) * bd.Box(16, 8, 2, align=_Z0)
               for x, y, a in _polar(36, 6)]
    return _cut(disc, *splines, *windows)


def _brake_drum(od: float) -> bd.Solid:
    r = od / 2
    drum = _revolved([(14, 0), (r, 0), (r, 50), (r + 4, 50), (r + 4, 55), (r - 7, 55),
                      (r - 7, 8), (14, 8)])
    return _cut(drum, *_bolt_holes(100, 5, 12, -1, 10))


def brake_builders() -> list[tuple[str, str, Builder]]:
    """Couplings, brake discs and drums, a clutch plate."""
    return [
        ("flange-coupling-d20", "Rigid flange coupling half, bore 20 mm, 4 bolts",
         lambda: _flange_coupling(20, 100, 14, 40, 40, 4)),
        ("flange-coupling-d32", "Rigid flange coupling half, bore 32 mm, 6 bolts",
         lambda: _flange_coupling(32, 140, 18, 60, 55, 6)),
        ("jaw-coupling-hub-d30-b10", "Jaw coupling hub 30 mm, bore 10 mm",
         lambda: _jaw_hub(30, 10, 12, 9)),
        ("jaw-coupling-hub-d40-b14", "Jaw coupling hub 40 mm, bore 14 mm",
         lambda: _jaw_hub(40, 14, 16, 12)),
        ("jaw-coupling-spider-d40", "Elastomer spider for 40 mm jaw coupling",
         lambda: _jaw_spider(40, 11)),
        ("rigid-sleeve-coupling-d10", "Rigid sleeve coupling, bore 10 mm",
         lambda: _sleeve_coupling(10, 20, 30)),
        ("rigid-sleeve-coupling-d16", "Rigid sleeve coupling, bore 16 mm",
         lambda: _sleeve_coupling(16, 30, 50)),
        ("brake-disc-solid-d200", "Solid hat-type brake disc 200 mm",
         lambda: _brake_disc(200, 40, 10, 40, 56)),
        ("brake-disc-drilled-d240", "Cross-drilled brake disc 240 mm", lambda: _drilled_disc(240)),
        ("brake-disc-vented-d280", "Internally vented brake disc 280 mm",
         lambda: _vented_disc(280)),
        ("clutch-plate-d180", "Clutch friction plate 180 mm, splined hub",
         lambda: _clutch_plate(180)),
        ("brake-drum-d160", "Brake drum 160 mm with 5 stud holes", lambda: _brake_drum(160)),
    ]


# --------------------------------------------------------------------------- casters, wheels


def _wheel(d: float, w: float, bore: float, holes: int = 0) -> bd.Solid:
    """Wheel about Z centred on z = 0: hub of width w, thin web, chamfered tyre."""
    rb, rh, r, rr = bore / 2, bore / 2 + 6, d / 2, d / 2 - (0.18 * d + 2)
    ww, tw, c = 0.2 * w, w / 2 - 2, 2.0
    wheel = _revolved([(rb, -w / 2), (rh, -w / 2), (rh, -ww), (rr, -ww), (rr, -tw),
                       (r - c, -tw), (r, -tw + c), (r, tw - c), (r - c, tw), (rr, tw), (rr, ww),
                       (rh, ww), (rh, w / 2), (rb, w / 2)])
    if holes == 0:
        return wheel
    lighten = [_cyl((rr - rh) * 0.3, w, x, y, -w / 2) for x, y, _ in _polar((rh + rr) / 2, holes)]
    return _cut(wheel, *lighten)


@dataclass(frozen=True)
class _Caster:
    """Caster layout: ground at z = 0, axle along X at the wheel centre, plate on top."""

    wheel_d: float
    wheel_w: float
    axle_d: float
    plate: float
    swivel: bool
    sheet: float = 3.0  # fork sheet thickness
    race_h: float = 8.0  # swivel race height between fork web and plate

    @property
    def web_z(self) -> float:
        return self.wheel_d + 5.0

    @property
    def plate_z(self) -> float:
        return self.web_z + self.sheet + (self.race_h if self.swivel else 0.0)


def _caster_wheel(c: _Caster) -> bd.Solid:
    wheel = _wheel(c.wheel_d, c.wheel_w, c.axle_d)
    return bd.Pos(0, 0, c.wheel_d / 2) * bd.Rot(0, 90, 0) * wheel


def _caster_fork(c: _Caster) -> bd.Solid:
    """U-shaped fork: two legs with axle holes and a square web on top."""
    half, leg_y, z0 = c.wheel_w / 2 + c.sheet / 2, 3 * c.axle_d, c.wheel_d / 2 - 1.5 * c.axle_d
    legs = [_box(c.sheet, leg_y, c.web_z - z0 + 0.5, x=s * half, z=z0) for s in (-1, 1)]
    web_side = max(c.wheel_w + 2 * c.sheet, 0.7 * c.plate)
    fork = _fuse(_box(web_side, web_side, c.sheet, z=c.web_z), *legs)
    axle_hole = bd.Pos(0, 0, c.wheel_d / 2) * bd.Rot(0, 90, 0) * bd.Cylinder(c.axle_d / 2, 400)
    return _cut(fork, axle_hole)


def _caster_axle(c: _Caster) -> bd.Solid:
    """Headed axle pin along +X; the head bears on the -X leg."""
    reach = c.wheel_w / 2 + c.sheet
    pin = bd.Pos(0, 0, -reach - 3) * _shaft([(1.6 * c.axle_d, 3), (c.axle_d, 2 * reach + 4)])
    return bd.Pos(0, 0, c.wheel_d / 2) * bd.Rot(0, 90, 0) * pin


def _caster_plate(c: _Caster) -> bd.Solid:
    """Top plate with four mounting holes; a swivel race underneath for swivel casters."""
    p, top = c.plate, c.plate_z
    q = p / 2 - p / 8
    holes = [_cyl(p / 16, 6, x, y, top - 1) for x in (-q, q) for y in (-q, q)]
    plate = _cut(_box(p, p, 4, z=top), *holes)
    if not c.swivel:
        return plate
    return _fuse(plate, _cyl(0.3 * p, c.race_h + 0.5, z=top - c.race_h))


def _caster(c: _Caster) -> bd.Solid:
    return _fuse(_caster_plate(c), _caster_fork(c), _caster_axle(c), _caster_wheel(c))


def _trolley_deck() -> bd.Solid:
    """Deck with four caster bolt patterns and two sockets for the push handle."""
    deck = bd.fillet(_box(440, 250, 18).edges().filter_by(bd.Axis.Z), radius=12)
    holes = [_cyl(4.25, 20, cx + dx, cy + dy, -1)
             for cx in (-150, 150) for cy in (-75, 75) for dx in (-30, 30) for dy in (-30, 30)]
    sockets = [_cyl(11.25, 20, -200, y, -1) for y in (-90, 90)]
    return _cut(deck, *holes, *sockets)


def _trolley_handle(width: float, height: float, bar_d: float) -> bd.Solid:
    """U-shaped push handle of round bar; spheres round off the two corners."""
    r, x = bar_d / 2, width / 2
    uprights = [_cyl(r, height, x=s * x) for s in (-1, 1)]
    corners = [bd.Pos(s * x, 0, height) * bd.Sphere(r) for s in (-1, 1)]
    grip = bd.Pos(0, 0, height) * bd.Rot(0, 90, 0) * bd.Cylinder(r, width)
    return _fuse(grip, *uprights, *corners)


_C50S = _Caster(50, 20, 8, 60, swivel=True)
_C75F = _Caster(75, 25, 10, 80, swivel=False)
_C75S = _Caster(75, 25, 10, 80, swivel=True)
_C100S = _Caster(100, 32, 12, 100, swivel=True)


def caster_builders() -> list[tuple[str, str, Builder]]:
    """Wheels, caster plates, forks and axles, whole casters, trolley deck and handle."""
    return [
        ("wheel-d50-b8", "Caster wheel 50x20 mm, bore 8 mm", lambda: _wheel(50, 20, 8)),
        ("wheel-d75-b10", "Caster wheel 75x25 mm, bore 10 mm", lambda: _wheel(75, 25, 10)),
        ("wheel-d100-b12", "Caster wheel 100x32 mm, bore 12 mm, lightening holes",
         lambda: _wheel(100, 32, 12, holes=5)),
        ("wheel-d125-b12", "Trolley wheel 125x38 mm, bore 12 mm, lightening holes",
         lambda: _wheel(125, 38, 12, holes=6)),
        ("caster-plate-swivel-60", "Swivel caster top plate 60 mm with race",
         lambda: _caster_plate(_C50S)),
        ("caster-plate-fixed-80", "Fixed caster top plate 80 mm", lambda: _caster_plate(_C75F)),
        ("caster-fork-d50", "Caster fork for 50x20 mm wheels", lambda: _caster_fork(_C50S)),
        ("caster-fork-d100", "Caster fork for 100x32 mm wheels", lambda: _caster_fork(_C100S)),
        ("caster-axle-d8", "Headed caster axle 8 mm", lambda: _caster_axle(_C50S)),
        ("caster-axle-d12", "Headed caster axle 12 mm", lambda: _caster_axle(_C100S)),
        ("swivel-caster-d50", "Swivel caster 50 mm, one solid", lambda: _caster(_C50S)),
        ("fixed-caster-d75", "Fixed caster 75 mm, one solid", lambda: _caster(_C75F)),
        ("swivel-caster-d100", "Swivel caster 100 mm, one solid", lambda: _caster(_C100S)),
        ("trolley-deck-440x250", "Trolley deck 440x250 mm with caster and handle holes",
         _trolley_deck),
        ("trolley-handle-u180", "U-shaped trolley push handle, 22 mm bar",
         lambda: _trolley_handle(180, 400, 22)),
    ]
