"""Tests of cadio.truth.mates, joints and contact: face mates, joints, pruning, invariance, goldens.

Synthetic assemblies (boxes, a drilled plate, a bolt, a cover on a micro-radian housing, a
gland beside a filleted shoulder, a countersunk screw, a collar on a B-spline bevel) pin down
each rule with hand-computed numbers; the real CAx-IF AS1, KCL pipe flange and KCL ball bearing
are checked against hand-verified JSON goldens in tests/golden/mates (parts named by instance
path, or by index and bounding box where the file names every solid NONE), and the PM4 pump's
covers and gland against what they were measured to be.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import build123d as bd
import numpy as np
import pandas as pd
import pytest
from OCP.Bnd import Bnd_Box
from OCP.BRepAlgoAPI import BRepAlgoAPI_Cut, BRepAlgoAPI_Fuse
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace, BRepBuilderAPI_MakePolygon
from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox, BRepPrimAPI_MakeCylinder, BRepPrimAPI_MakePrism
from OCP.gp import gp_Ax2, gp_Dir, gp_Pnt, gp_Trsf, gp_Vec
from OCP.TopAbs import TopAbs_SOLID
from OCP.TopExp import TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Shape
from scipy.spatial.transform import Rotation

from cadio.cad.faces import indexed_faces, recognise_faces
from cadio.cad.step import StepSolid
from cadio.records import SolidInfo
from cadio.tolerances import DEFAULT_TOLERANCES as TOL
from cadio.truth.joints import CAD_NAMES, Constraint, classify_motion, derive_joint
from cadio.truth.mates import COLUMNS, extract_mates, read_assembly_mates, read_mates, write_mates
from cadio.truth.relations import PairContact, relate

GOLDEN = Path(__file__).parent / "golden" / "mates"
DIRECTIONAL = {"left", "right", "above", "below", "front", "behind"}

# ---------------------------------------------------------------- synthetic parts (mm)


def _solid(shape: TopoDS_Shape) -> TopoDS_Shape:
    explorer = TopExp_Explorer(shape, TopAbs_SOLID)
    return TopoDS.Solid_s(explorer.Current())


def box(x: float, y: float, z: float, dx: float, dy: float, dz: float) -> TopoDS_Shape:
    return BRepPrimAPI_MakeBox(gp_Pnt(x, y, z), dx, dy, dz).Shape()


def cylinder(x: float, y: float, z: float, r: float, h: float) -> TopoDS_Shape:
    return BRepPrimAPI_MakeCylinder(gp_Ax2(gp_Pnt(x, y, z), gp_Dir(0, 0, 1)), r, h).Shape()


def fuse(*shapes: TopoDS_Shape) -> TopoDS_Shape:
    out = shapes[0]
    for s in shapes[1:]:
        out = BRepAlgoAPI_Fuse(out, s).Shape()
    return _solid(out)


def drilled_plate(r_hole: float) -> TopoDS_Shape:
    """Plate 60x40x10 (z 0..10) with a through hole of radius r_hole at (20, 20)."""
    return _solid(BRepAlgoAPI_Cut(box(0, 0, 0, 60, 40, 10), cylinder(20, 20, -1, r_hole, 12))
                  .Shape())


def assembly(*named: tuple[str, TopoDS_Shape]) -> list[StepSolid]:
    return [StepSolid(SolidInfo(k, name, "", np.eye(4), f"asm/{name}"), _solid(shape))
            for k, (name, shape) in enumerate(named)]


def bolted() -> list[StepSolid]:
    """A drilled plate, a block resting on it, a bolt (shank r=5 fitting the hole, head r=8 on
    the plate top z=10)."""
    return assembly(
        ("plate", drilled_plate(5.0)),
        ("block", box(35, 10, 10, 20, 20, 5)),
        ("bolt", fuse(cylinder(20, 20, -5, 5, 15), cylinder(20, 20, 10, 8, 3))),
    )


def rows(table: pd.DataFrame, a: int, b: int, level: str, relation: str | None = None
         ) -> pd.DataFrame:
    sel = (table.index_a == a) & (table.index_b == b) & (table.level == level)
    if relation is not None:
        sel &= table.relation == relation
    return table[sel]


# ---------------------------------------------------------------- face mates on synthetic parts


def test_table_has_the_documented_columns() -> None:
    table = extract_mates(bolted(), assembly="bolted").table
    assert tuple(table.columns) == COLUMNS
    assert set(table.level) == {"face", "part", "joint"}
    assert (table.index_a < table.index_b).all()
    assert (table.assembly == "bolted").all()


def test_block_on_plate_is_coincident_with_its_footprint_and_planar() -> None:
    table = extract_mates(bolted()).table
    mate = rows(table, 0, 1, "face", "coincident")
    assert len(mate) == 1
    assert mate.overlap_area_mm2.iloc[0] == pytest.approx(20 * 20, rel=1e-6)
    assert mate.distance_mm.iloc[0] <= TOL.contact_mm
    assert np.allclose(mate.axis.iloc[0], [0, 0, 1])  # plate's outward normal
    assert np.allclose(mate.origin.iloc[0], [45, 20, 10])  # centre of the footprint
    joint = rows(table, 0, 1, "joint").iloc[0]
    assert (joint.relation, joint.kinematic, joint.dof) == ("planar", "planar", 3)
    assert np.allclose(np.abs(joint.axis), [0, 0, 1])
    assert (joint.onshape, joint.freecad, joint.fusion360) == ("Planar", "Planar", "Planar")


def test_bolt_is_revolute_by_geometry_and_fastened_by_name() -> None:
    table = extract_mates(bolted()).table
    fit = rows(table, 0, 2, "face", "concentric").iloc[0]
    assert fit.fit == "fit" and fit.radial_gap_mm == pytest.approx(0.0, abs=1e-9)
    head = rows(table, 0, 2, "face", "coincident").iloc[0]
    assert head.overlap_area_mm2 == pytest.approx(math.pi * (8**2 - 5**2), rel=1e-6)
    joint = rows(table, 0, 2, "joint").iloc[0]
    assert (joint.kinematic, joint.dof, joint.relation) == ("revolute", 1, "fastened")
    assert np.allclose(np.abs(joint.axis), [0, 0, 1])
    assert np.allclose(joint.origin[:2], [20, 20])  # on the bolt's axis
    assert (joint.onshape, joint.freecad, joint.fusion360) == ("Fastened", "Fixed", "Rigid")
    assert "fastener by name" in joint.evidence


def test_shaft_in_a_clearance_hole_is_concentric_without_contact() -> None:
    """1 mm of radial clearance, exactly ``concentric_gap_mm``: a mate (values at a tolerance
    count as inside), a clearance, and still a shaft in a bore for the joint."""
    parts = assembly(("plate", drilled_plate(5.0)), ("shaft", cylinder(20, 20, -20, 4.0, 50)))
    result = extract_mates(parts)
    mate = rows(result.table, 0, 1, "face", "concentric").iloc[0]
    assert mate.fit == "clearance" and mate.radial_gap_mm == pytest.approx(1.0, abs=1e-9)
    assert result.n_contact_pairs == 0  # 1 mm of clearance all round
    joint = rows(result.table, 0, 1, "joint").iloc[0]
    assert (joint.kinematic, joint.dof) == ("cylindrical", 2)
    looser = assembly(("plate", drilled_plate(5.0)), ("shaft", cylinder(20, 20, -20, 3.99, 50)))
    table = extract_mates(looser).table
    assert rows(table, 0, 1, "face").empty and rows(table, 0, 1, "joint").empty


def circle_edges(shape: bd.Shape, radius: float, z: float) -> list[bd.Edge]:
    return [e for e in shape.edges().filter_by(bd.GeomType.CIRCLE)
            if abs(e.radius - radius) < 1e-6 and abs(e.center().Z - z) < 1e-6]


def gland_beside_shoulder(fillet: float) -> list[StepSolid]:
    """A shaft (r=10 up to z=30, r=6 above) and a gland (bore r=6.5, outer r=10) slid down to
    0.4 mm above the shoulder, both r=10 edges at the gap rounded by ``fillet`` mm: their r=10
    cylinders end 0.4 + 2 * fillet mm apart along the axis."""
    shaft = bd.Cylinder(10, 30, align=bd.Align.NONE) + bd.Pos(0, 0, 30) * bd.Cylinder(
        6, 30, align=bd.Align.NONE)
    gland = bd.Pos(0, 0, 30.4) * (bd.Cylinder(10, 9.6, align=bd.Align.NONE)
                                  - bd.Cylinder(6.5, 9.6, align=bd.Align.NONE))
    shaft = bd.fillet(circle_edges(shaft, 10, 30), fillet)
    gland = bd.fillet(circle_edges(gland, 10, 30.4), fillet)
    return assembly(("shaft", shaft.solids()[0].wrapped), ("gland", gland.solids()[0].wrapped))


def face_kinds(solid: StepSolid) -> dict[int, str]:
    return {p.face_id: f"{p.kind} r={p.radius:.3f}"
            for p in recognise_faces(indexed_faces(solid.shape)) if p.kind != "plane"}


def concentric_by_faces(solids: list[StepSolid], a: int, b: int) -> dict[tuple[str, str], Any]:
    """The concentric mates of parts a < b keyed by their faces' kinds and radii."""
    table = extract_mates(solids).table
    ka, kb = face_kinds(solids[a]), face_kinds(solids[b])
    found = rows(table, a, b, "face", "concentric")
    keyed = {(ka[r.face_a], kb[r.face_b]): r for _, r in found.iterrows()}
    assert len(keyed) == len(found)  # one row per face pair
    return keyed


def test_gland_beside_a_shaft_across_fillets_is_a_concentric_mate() -> None:
    """Faces 0.8 mm apart (<= concentric_gap_mm) are a mate, whatever their axial overlap; the
    gland's bore round the thinner shaft is another, and the only shaft in a bore."""
    solids = gland_beside_shoulder(0.2)
    mates = concentric_by_faces(solids, 0, 1)
    assert set(mates) == {("cylinder r=10.000", "cylinder r=10.000"),
                          ("cylinder r=6.000", "cylinder r=6.500")}
    beside = mates[("cylinder r=10.000", "cylinder r=10.000")]
    assert (beside.fit, beside.radial_gap_mm) == ("fit", pytest.approx(0.0, abs=1e-9))
    assert "0.8000 mm apart" in beside.evidence and "shaft in a bore" not in beside.evidence
    bore = mates[("cylinder r=6.000", "cylinder r=6.500")]
    assert (bore.fit, bore.radial_gap_mm) == ("clearance", pytest.approx(0.5, abs=1e-9))
    joint = rows(extract_mates(solids).table, 0, 1, "joint").iloc[0]
    assert (joint.kinematic, joint.evidence.endswith("1 shafts in bores")) == ("cylindrical", True)
    wider = concentric_by_faces(gland_beside_shoulder(0.5), 0, 1)  # 1.4 mm apart: no mate
    assert set(wider) == {("cylinder r=6.000", "cylinder r=6.500")}


def countersunk_screw() -> list[StepSolid]:
    plate = (bd.Pos(0, 0, 5) * bd.Box(40, 40, 10) - bd.Pos(0, 0, 5) * bd.Cylinder(3.2, 12)
             - bd.Pos(0, 0, 9.1) * bd.Cone(3.2, 7.0, 3.8))
    screw = bd.Pos(0, 0, 1) * bd.Cylinder(3, 12) + bd.Pos(0, 0, 8.5) * bd.Cone(3, 6, 3)
    return assembly(("plate", plate.solids()[0].wrapped), ("screw", screw.solids()[0].wrapped))


@pytest.mark.shared
def test_pm4_gland_beside_the_impeller_is_concentric(pm4: list[StepSolid]) -> None:
    """Gland_2 sits 0.43 mm from the impeller's hub: equal r=8.5 bores, and the gland's r=13.5
    boss beside the hub's cone, across fillets; neither overlaps the other along the axis."""
    solids = named(pm4, "Gland_2", "Impeller")
    mates = rows(extract_mates(solids).table, 0, 1, "face", "concentric")
    got = sorted((m.fit, round(m.radial_gap_mm, 3)) for _, m in mates.iterrows())
    assert got == [("clearance", 0.519), ("fit", 0.0)]
    assert all("axial overlap" in e and "shaft in a bore" not in e for e in mates.evidence)


def test_countersunk_screw_has_a_cone_fit_and_clearances() -> None:
    """A 45 degree countersink (r 3.2 at z=7.2 to r 6 at z=10) holding a screw whose head cone
    matches it, shank r=3 in the r=3.2 hole: cone in cone is a fit, cylinder in cylinder and
    cylinder against cone are clearances; the seated cone stops the screw along its axis."""
    solids = countersunk_screw()
    mates = concentric_by_faces(solids, 0, 1)
    (seat,) = [m for (a, b), m in mates.items() if a.startswith("cone") and b.startswith("cone")]
    assert (seat.fit, seat.radial_gap_mm) == ("fit", pytest.approx(0.0, abs=1e-6))
    shank = mates[("cylinder r=3.200", "cylinder r=3.000")]
    assert (shank.fit, shank.radial_gap_mm) == ("clearance", pytest.approx(0.2, abs=1e-9))
    mixed = [m.fit for (a, b), m in mates.items() if a[:4] != b[:4]]
    assert mixed and set(mixed) == {"clearance"}
    joint = rows(extract_mates(solids).table, 0, 1, "joint").iloc[0]
    assert (joint.kinematic, joint.relation) == ("revolute", "fastened")  # "screw" by name
    assert np.allclose(np.abs(joint.axis), [0, 0, 1]) and np.allclose(joint.origin[:2], 0)


def test_collar_seated_on_a_bspline_bevel_cone_is_a_fit(trimmed_bspline) -> None:
    """The pipe's bevel is stored as the KCL pipe stores its own (OCCT's converter raises on it);
    a collar's conical bore sits on it."""
    pipe = bd.Cylinder(10, 20) + bd.Pos(0, 0, 13) * bd.Cone(10, 6, 6)  # bevel z 10..16
    collar = bd.Pos(0, 0, 14.25) * bd.Cylinder(14, 2.5) - bd.Pos(0, 0, 13) * bd.Cone(10, 6, 6)
    solids = assembly(("pipe", trimmed_bspline(pipe.solids()[0].wrapped)),
                      ("collar", collar.solids()[0].wrapped))
    table = extract_mates(solids).table
    ((_, seat),) = rows(table, 0, 1, "face", "concentric").iterrows()
    assert (seat.fit, seat.radial_gap_mm) == ("fit", pytest.approx(0.0, abs=1e-6))
    assert face_kinds(solids[0])[seat.face_a].startswith("cone")
    joint = rows(table, 0, 1, "joint").iloc[0]
    assert (joint.kinematic, joint.dof) == ("revolute", 1)


def test_coaxial_but_far_apart_along_the_axis_is_no_mate() -> None:
    parts = assembly(("plate", drilled_plate(5.0)), ("pin", cylinder(20, 20, 30, 4.0, 10)))
    assert rows(extract_mates(parts).table, 0, 1, "face").empty


def test_touching_along_an_edge_only_is_no_mate() -> None:
    parts = assembly(("a", box(0, 0, 0, 10, 10, 10)), ("b", box(10, 0, 10, 10, 10, 10)))
    result = extract_mates(parts)
    assert result.n_contact_pairs == 1  # the exact distance is 0 ...
    assert rows(result.table, 0, 1, "face", "coincident").empty  # ... but no area in common
    assert rows(result.table, 0, 1, "joint").empty


def prism(profile: list[tuple[float, float]], y0: float, width: float) -> TopoDS_Shape:
    """A prism: the (x, z) polygon ``profile`` at y = y0, extruded ``width`` mm along +Y."""
    polygon = BRepBuilderAPI_MakePolygon()
    for x, z in profile:
        polygon.Add(gp_Pnt(x, y0, z))
    polygon.Close()
    face = BRepBuilderAPI_MakeFace(polygon.Wire(), True).Face()
    return BRepPrimAPI_MakePrism(face, gp_Vec(0, width, 0)).Shape()


def seated_cover(gap: float) -> list[StepSolid]:
    """A housing whose top rises 2e-6 mm per mm over a flat bottom, and a 10 mm cover plate
    (40 x 30 mm) lying ``gap`` mm above that top, parallel to it. The housing's top and bottom
    form one plane group whose normal lies between theirs, a micro-radian off the top's own."""
    def top(x: float) -> float:
        return 10.0 + 2e-6 * x

    housing = prism([(0, 0), (100, 0), (100, top(100)), (0, top(0))], 0.0, 50.0)
    cover = prism([(x, top(x) + gap + dz) for x, dz in ((30, 0), (70, 0), (70, 10), (30, 10))],
                  10.0, 30.0)
    return assembly(("housing", housing), ("cover", cover))


@pytest.mark.parametrize(("gap", "mated"), [(0.0, True), (0.05, True), (0.2, False)])
def test_cover_seated_on_its_housing_is_coincident_up_to_the_contact_tolerance(
        gap: float, mated: bool) -> None:
    result = extract_mates(seated_cover(gap))
    mates = rows(result.table, 0, 1, "face", "coincident")
    joints = rows(result.table, 0, 1, "joint")
    assert len(mates) == int(mated) and len(joints) == int(mated)
    assert result.n_contact_pairs == int(mated)
    if mated:
        assert mates.overlap_area_mm2.iloc[0] == pytest.approx(40 * 30, rel=1e-6)
        assert mates.distance_mm.iloc[0] == pytest.approx(gap, abs=1e-6)
        assert joints.kinematic.iloc[0] == "planar"


@pytest.fixture(scope="module")
def pm4(shared_step_dir: Path) -> list[StepSolid]:
    from cadio.cad.step import read_step

    return read_step(shared_step_dir / "assemblies" / "occt_pm4_rotor-pump-assembly.stp")


def named(solids: list[StepSolid], *names: str) -> list[StepSolid]:
    """The solids of these names, in file order, renumbered 0, 1, ..."""
    found = [s for s in solids if s.info.name in names]
    assert sorted(s.info.name for s in found) == sorted(names)
    return [StepSolid(replace(s.info, index=k), s.shape) for k, s in enumerate(found)]


@pytest.mark.shared
def test_pm4_covers_are_coincident(pm4: list[StepSolid]) -> None:
    """The PM4 pump's two covers meet on two faces whose planes differ by 1e-7 rad."""
    mates = rows(extract_mates(named(pm4, "Cover_Up", "Cover_Bottom")).table, 0, 1, "face",
                 "coincident")
    assert sorted(mates.overlap_area_mm2) == [pytest.approx(333.979, abs=1e-3),
                                              pytest.approx(3399.162, abs=1e-3)]


def test_block_in_a_guide_slides_and_in_a_corner_is_fastened() -> None:
    guide = fuse(box(0, 0, 0, 100, 40, 10), box(0, 0, 10, 100, 10, 20))
    corner = fuse(box(0, 0, 0, 100, 40, 10), box(0, 0, 10, 100, 10, 20), box(0, 0, 10, 10, 40, 20))
    parts = assembly(("guide", guide), ("slider", box(30, 10, 10, 20, 20, 10)),
                     ("corner", corner.Moved(_shift(0, 200, 0))),
                     ("wedged", box(10, 210, 10, 20, 20, 10)))
    table = extract_mates(parts).table
    slide = rows(table, 0, 1, "joint").iloc[0]
    assert (slide.kinematic, slide.dof) == ("slider", 1)
    assert np.allclose(np.abs(slide.axis), [1, 0, 0])
    fixed = rows(table, 2, 3, "joint").iloc[0]
    assert (fixed.kinematic, fixed.dof, fixed.onshape) == ("fastened", 0, "Fastened")


def assert_part_level_is_face_level(table: pd.DataFrame) -> None:
    """The part-level concentric / coincident pairs are exactly the pairs with a face mate of
    that kind: what the relation stage scores against is the CAD's mates."""
    for relation in ("concentric", "coincident"):
        pairs = {level: set(zip(*(table[(table.level == level) & (table.relation == relation)]
                                  [c] for c in ("index_a", "index_b")), strict=True))
                 for level in ("face", "part")}
        assert pairs["part"] == pairs["face"], relation


def test_part_level_rows_are_the_face_mates_and_the_dominant_directions() -> None:
    solids = bolted()
    table = extract_mates(solids).table
    assert_part_level_is_face_level(table)
    from cadio.cad.features import extract_features

    feats = [extract_features(s.shape) for s in solids]
    for a in range(3):
        for b in range(a + 1, 3):
            part = set(rows(table, a, b, "part").relation)
            faces = set(rows(table, a, b, "face").relation)
            contact = PairContact(coincident="coincident" in faces,
                                  concentric="concentric" in faces)
            expected = {r.value for r in relate(feats[a], feats[b], contact=contact).holding()}
            assert part == expected, (a, b)
    assert table.attrs["near_boundary"] == []  # every contact of the bolted joint is exact


def test_a_sample_assembly_is_scored_on_its_face_mates() -> None:
    """The sleeve coupling: each shaft in the sleeve's bore (a fit), the shafts 2 mm apart
    end to end (no mate); bearing housing: the shaft through the bearing, the bearing seated."""
    from cadio.samples.assemblies import assembly_builders

    builders = {name: build for name, _, build in assembly_builders()}
    for name in ("sleeve-coupling-d10", "bearing-housing-608"):
        parts = builders[name]()
        solids = [StepSolid(SolidInfo(k, str(p.label), "", np.eye(4), f"{name}/{p.label}"),
                            TopoDS.Solid_s(p.wrapped)) for k, p in enumerate(parts)]
        table = extract_mates(solids, assembly=name).table
        assert_part_level_is_face_level(table)
        concentric = table[(table.level == "part") & (table.relation == "concentric")]
        assert len(concentric) >= 2, name
    sleeve = extract_mates([StepSolid(SolidInfo(k, str(p.label), "", np.eye(4), str(p.label)),
                                      TopoDS.Solid_s(p.wrapped))
                            for k, p in enumerate(builders["sleeve-coupling-d10"]())]).table
    assert set(rows(sleeve, 0, 1, "part").relation) >= {"concentric"}
    assert set(rows(sleeve, 0, 2, "part").relation) >= {"concentric"}
    assert not {"concentric", "coincident"} & set(rows(sleeve, 1, 2, "part").relation)


def test_near_misses_are_named_in_the_metadata() -> None:
    """A cover 0.15 mm above its housing: no coincident mate, but within the margins."""
    solids = assembly(("housing", box(0, 0, 0, 40, 40, 10)),
                      ("cover", box(5, 5, 10.15, 20, 20, 2)))
    result = extract_mates(solids, part_ids={0: "h", 1: "c"})
    assert "coincident" not in set(result.level("part").relation)
    assert result.table.attrs["near_boundary"] == [["h", "c", "coincident"]]


# ---------------------------------------------------------------- joints from constraints


def _plane(n: tuple[float, ...], p: tuple[float, ...]) -> Constraint:
    return Constraint("plane", np.array(n, float), np.array(p, float))


def _axis(d: tuple[float, ...], p: tuple[float, ...]) -> Constraint:
    return Constraint("axis", np.array(d, float), np.array(p, float))


@pytest.mark.parametrize(("constraints", "kind", "dof", "axis"), [
    ([_plane((0, 0, 1), (5, 5, 0))], "planar", 3, (0, 0, 1)),
    ([_plane((0, 0, 1), (5, 5, 0)), _plane((0, 0, -1), (40, 5, 0))], "planar", 3, (0, 0, 1)),
    ([_plane((0, 0, 1), (5, 5, 0)), _plane((1, 0, 0), (0, 5, 5))], "slider", 1, (0, 1, 0)),
    ([_plane((0, 0, 1), (5, 5, 0)), _plane((1, 0, 0), (0, 5, 5)), _plane((0, 1, 0), (5, 0, 5))],
     "fastened", 0, None),
    ([_axis((0, 0, 1), (10, 20, 0))], "cylindrical", 2, (0, 0, 1)),
    ([_axis((0, 0, 1), (10, 20, 5)), _plane((0, 0, -1), (13, 20, 30))], "revolute", 1, (0, 0, 1)),
    ([_axis((0, 0, 1), (10, 20, 5)), _axis((0, 0, 1), (50, 20, 5))], "slider", 1, (0, 0, 1)),
    ([_axis((0, 0, 1), (10, 20, 5)), _plane((1, 0, 0), (15, 20, 0))], "slider", 1, (0, 0, 1)),
    ([_axis((0, 0, 1), (0, 0, 0)), _axis((1, 0, 0), (0, 0, 0))], "fastened", 0, None),
])
def test_classify_motion(constraints: list[Constraint], kind: str, dof: int,
                         axis: tuple[float, ...] | None) -> None:
    got_kind, got_dof, got_axis, _ = classify_motion(constraints)
    assert (got_kind, got_dof) == (kind, dof)
    if axis is None:
        assert got_axis is None
    else:
        assert np.allclose(np.abs(got_axis), axis)


def test_revolute_origin_is_on_the_axis_and_moves_with_the_parts() -> None:
    rot = Rotation.from_euler("xyz", [30, -50, 70], degrees=True).as_matrix()
    shift = np.array([5.0, -7.0, 11.0])
    cons = [_axis((0, 0, 1), (10, 20, 5)), _plane((0, 0, -1), (13, 20, 30))]
    moved = [Constraint(c.kind, rot @ c.direction, rot @ c.point + shift) for c in cons]
    _, _, axis, origin = classify_motion(cons)
    _, _, axis2, origin2 = classify_motion(moved)
    assert np.allclose(origin[:2], [10, 20])
    assert np.allclose(origin2, rot @ origin + shift)
    assert np.allclose(np.abs(axis2 @ (rot @ axis)), 1.0)


def test_two_contacts_a_fraction_of_a_degree_apart_are_one_direction() -> None:
    tilt = math.radians(0.4)
    cons = [_plane((0, 0, 1), (0, 0, 0)), _plane((0, math.sin(tilt), math.cos(tilt)), (50, 0, 0))]
    assert classify_motion(cons)[0] == "planar"


def test_suggestion_and_cad_names() -> None:
    joint = derive_joint([_axis((0, 0, 1), (0, 0, 0))], ("rod", "bracket"))
    assert joint is not None and joint.suggested == joint.kinematic == "cylindrical"
    assert derive_joint([], ("bolt", "plate")) is None
    assert set(CAD_NAMES) == {"fastened", "revolute", "slider", "cylindrical", "planar"}
    assert CAD_NAMES["fastened"] == {"onshape": "Fastened", "freecad": "Fixed",
                                     "fusion360": "Rigid"}


# ---------------------------------------------------------------- invariance and I/O


def _shift(x: float, y: float, z: float) -> TopLoc_Location:
    trsf = gp_Trsf()
    trsf.SetTranslation(gp_Vec(x, y, z))
    return TopLoc_Location(trsf)


def _moved(solids: list[StepSolid], rot: np.ndarray, shift: np.ndarray) -> list[StepSolid]:
    trsf = gp_Trsf()
    trsf.SetValues(*rot[0], shift[0], *rot[1], shift[1], *rot[2], shift[2])
    return [StepSolid(s.info, TopoDS.Solid_s(s.shape.Moved(TopLoc_Location(trsf))))
            for s in solids]


def _keyed(table: pd.DataFrame, skip_directional: bool) -> dict[tuple, Any]:
    keep = ~table.relation.isin(DIRECTIONAL) if skip_directional else table.relation.notna()
    cols = ["index_a", "index_b", "level", "relation", "face_a", "face_b", "fit", "kinematic"]
    return {tuple(r[c] for c in cols): r for _, r in table[keep].iterrows()}


def assert_invariant(before: pd.DataFrame, after: pd.DataFrame, rot: np.ndarray,
                     shift: np.ndarray, skip_directional: bool = True) -> None:
    """Same rows; axes turned (sign free), origins moved, distances and areas unchanged."""
    a, b = _keyed(before, skip_directional), _keyed(after, skip_directional)
    assert a.keys() == b.keys()
    for key, row in a.items():
        other = b[key]
        if row.axis is not None:
            assert abs(float(np.dot(rot @ np.asarray(row.axis), other.axis))) == pytest.approx(1)
        if row.origin is not None:
            assert np.allclose(rot @ np.asarray(row.origin) + shift, other.origin, atol=1e-5)
        for col in ("overlap_area_mm2", "radial_gap_mm"):
            assert other[col] == pytest.approx(row[col], rel=1e-6, abs=1e-6, nan_ok=True)


def test_moving_the_whole_assembly_changes_nothing() -> None:
    guide = fuse(box(0, 0, 0, 100, 40, 10), box(0, 0, 10, 100, 10, 20)).Moved(_shift(0, 100, 0))
    solids = bolted() + assembly(("guide", guide), ("slider", box(30, 110, 10, 20, 20, 10)))
    solids = [StepSolid(SolidInfo(k, s.info.name, "", np.eye(4), s.info.path_in_assembly),
                        s.shape) for k, s in enumerate(solids)]
    rot = Rotation.from_euler("xyz", [37, -61, 113], degrees=True).as_matrix()
    shift = np.array([250.0, -1234.5, 77.7])
    before = extract_mates(solids)
    after = extract_mates(_moved(solids, rot, shift))
    assert after.n_contact_pairs == before.n_contact_pairs
    assert set(before.level("joint").kinematic) == {"planar", "revolute", "slider"}
    assert_invariant(before.table, after.table, rot, shift)


@pytest.mark.parametrize("build", [lambda: gland_beside_shoulder(0.2), countersunk_screw,
                                   lambda: seated_cover(0.0)])
def test_concentric_and_seated_mates_do_not_move_with_the_assembly(build: Any) -> None:
    solids = build()
    rot = Rotation.from_euler("xyz", [-23, 48, 131], degrees=True).as_matrix()
    shift = np.array([-500.0, 42.0, 3000.0])
    before, after = extract_mates(solids), extract_mates(_moved(solids, rot, shift))
    assert after.n_contact_pairs == before.n_contact_pairs
    assert len(before.level("face")) > 0
    assert_invariant(before.table, after.table, rot, shift)


def test_turning_about_z_with_the_view_axis_changes_nothing_at_all() -> None:
    solids = bolted()
    rot = Rotation.from_euler("z", 71, degrees=True).as_matrix()
    shift = np.array([10.0, 20.0, -30.0])
    before = extract_mates(solids).table
    after = extract_mates(_moved(solids, rot, shift), view_axis=rot @ [0.0, 1.0, 0.0]).table
    assert_invariant(before, after, rot, shift, skip_directional=False)


def test_write_and_read_back(tmp_path: Path) -> None:
    table = extract_mates(bolted(), assembly="bolted").table
    path = tmp_path / "mates" / "bolted.parquet"
    write_mates(path, table)
    back = read_mates(path)
    assert list(back.columns) == list(table.columns) and len(back) == len(table)
    assert back.attrs.get("tolerances") == TOL.as_dict()
    assert list(path.parent.iterdir()) == [path]  # no temporary file left behind


# ---------------------------------------------------------------- real assemblies (goldens)


def _bbox(shape: TopoDS_Shape) -> np.ndarray:
    box = Bnd_Box()
    BRepBndLib.Add_s(shape, box, False)
    return np.array(box.Get()).reshape(2, 3)


def _resolve(golden: dict[str, Any], solids: list[StepSolid]) -> dict[str, int]:
    """Alias -> solid index, by instance path or by index checked against a bounding box."""
    out = {}
    for alias, spec in golden["instances"].items():
        if "path" in spec:
            hits = [s.info.index for s in solids if s.info.path_in_assembly == spec["path"]]
            assert len(hits) == 1, f"{alias}: {spec['path']} matches {len(hits)} solids"
            out[alias] = hits[0]
        else:
            k = spec["index"]
            assert np.allclose(_bbox(solids[k].shape), spec["bbox"], atol=0.2), alias
            out[alias] = k
    return out


def _pair(table: pd.DataFrame, ids: dict[str, int], entry: dict[str, Any], level: str
          ) -> pd.DataFrame:
    a, b = sorted((ids[entry["a"]], ids[entry["b"]]))
    return rows(table, a, b, level)


def check_golden(golden: dict[str, Any], solids: list[StepSolid], table: pd.DataFrame) -> None:
    ids = _resolve(golden, solids)
    for key, count in golden["counts"].items():
        level, _, relation = key.partition("/")
        sel = table.level == level
        if relation:
            sel &= table.relation == relation
        assert int(sel.sum()) == count, key
    for e in golden["face"]:
        found = _pair(table, ids, e, "face")
        found = found[found.relation == e["relation"]]
        if "fit" in e:
            found = found[found.fit == e["fit"]]
        assert len(found) >= 1, e
        row = found.iloc[0]
        for col in ("radial_gap_mm", "overlap_area_mm2"):
            if col in e:
                assert row[col] == pytest.approx(e[col], rel=1e-3, abs=1e-3), e
        if "axis" in e:
            assert abs(float(np.dot(row.axis, e["axis"]))) == pytest.approx(1.0, abs=1e-6), e
        if "origin_on_axis" in e:
            rel = np.asarray(row.origin) - e["origin_on_axis"]
            assert np.linalg.norm(np.cross(rel, e["axis"])) <= TOL.coaxial_mm, e
    for e in golden["joints"]:
        joint = _pair(table, ids, e, "joint")
        assert len(joint) == 1, e
        row = joint.iloc[0]
        assert (row.kinematic, row.relation) == (e["kinematic"], e["suggested"]), e
        if "axis" in e:
            assert abs(float(np.dot(row.axis, e["axis"]))) == pytest.approx(1.0, abs=1e-6), e
    for e in golden.get("part", []):
        assert e["relation"] in set(_pair(table, ids, e, "part").relation), e
    for e in golden.get("absent_part", []):
        assert e["relation"] not in set(_pair(table, ids, e, "part").relation), e
    for e in golden["absent"]:
        assert _pair(table, ids, e, "face").empty, e
    for e in golden["absent_joints"]:
        assert _pair(table, ids, e, "joint").empty, e


@pytest.mark.shared
@pytest.mark.parametrize("name", ["as1", "pipe_flange", "ball_bearing"])
def test_real_assembly_matches_hand_checked_golden(name: str, shared_step_dir: Path) -> None:
    golden = json.loads((GOLDEN / f"{name}.json").read_text())
    from cadio.cad.step import read_step

    solids = read_step(shared_step_dir / golden["file"])
    table = extract_mates(solids).table
    check_golden(golden, solids, table)
    assert_part_level_is_face_level(table)


@pytest.mark.shared
def test_real_assembly_is_invariant_under_a_rigid_motion(shared_step_dir: Path) -> None:
    from cadio.cad.step import read_step

    solids = read_step(shared_step_dir / "assemblies" / "occt_as1-oc-214-mat.stp")
    rot = Rotation.from_euler("xyz", [-23, 48, 131], degrees=True).as_matrix()
    shift = np.array([-500.0, 42.0, 3000.0])
    before = extract_mates(solids)
    after = extract_mates(_moved(solids, rot, shift))
    assert (after.n_box_pairs >= after.n_contact_pairs == before.n_contact_pairs)
    assert_invariant(before.table, after.table, rot, shift)


@pytest.mark.shared
def test_read_assembly_mates_names_the_assembly(shared_step_dir: Path) -> None:
    result = read_assembly_mates(shared_step_dir / "assemblies" / "occt_as1-oc-214-mat.stp")
    assert set(result.table.assembly) == {"occt_as1-oc-214-mat"}
    assert result.n_pairs == 18 * 17 // 2 and result.seconds["read"] > 0
