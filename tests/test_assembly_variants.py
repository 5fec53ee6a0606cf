"""Tests of the assembly variant families: seeded draws, reproducible files, no interference,
and the face mates each layout promises found by the ground truth (through ingest and mates)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import build123d as bd
import pandas as pd
import pytest

from cadio.cad.ingest import IngestConfig, ingest
from cadio.cad.step import read_step
from cadio.samples.assembly_kit import SIZES, Mate, bolt, metric, nut, washer
from cadio.samples.assembly_variants import (
    FAMILIES,
    VARIANTS_INDEX,
    VariantEntry,
    draw_assembly_variant,
    draw_assembly_variants,
    missing_mates,
    overlaps,
    read_assembly_variants,
    write_assembly_variants,
)
from cadio.samples.parts import _box
from cadio.sandbox import Limits
from cadio.truth.assemblies import assembly_jobs, extract_assembly_mates
from cadio.truth.mates import read_assembly_mates, read_mates
from cadio.workspace import Workspace

REPO = Path(__file__).resolve().parents[1]
# Seed whose first draw of each family is quick (two cap screws, three flange bolts, gears of
# 21 and 26 teeth) and covers the options the checks need (two bearings of one colour,
# butting shafts, screwed pillow blocks).
AUDIT_SEED = 109
# Three small ones that ingest and the mates stage read as a library; with SMALL_SEED: two
# bearings (parts of one colour), a fixed caster, a sleeve coupling whose shafts butt.
SMALL, SMALL_SEED = ("bearing-shaft", "caster", "sleeve-coupling"), 4
# The families without a shaft in a bore; four draws of each with SLIDE_SEED cover every joint
# their options give (fitted and loose carriages, fitted and standard keys, a shoulder or not).
SLIDES, SLIDE_SEED = ("slide-guide", "rail-carriage", "keyed-hub"), 7


def test_draws_depend_only_on_seed_family_and_index() -> None:
    count = 2 * len(FAMILIES)
    first, again = draw_assembly_variants(count, seed=5), draw_assembly_variants(count, seed=5)
    assert [v.description for v in first] == [v.description for v in again]
    assert [v.description for v in first] != [v.description for v in draw_assembly_variants(
        count, seed=6)]
    assert [v.family for v in first[:len(FAMILIES)]] == list(FAMILIES)
    assert len({v.name for v in first}) == count
    for v in first:  # the same variant whatever the count or the families asked for
        alone = draw_assembly_variants(v.index + 1, seed=5, families=[v.family])[-1]
        assert (alone.name, alone.description) == (v.name, v.description)
        assert len(v.parts) == len(set(v.parts)) == len(v.categories)
        assert {m.a for m in v.mates} | {m.b for m in v.mates} <= set(v.parts)
    with pytest.raises(ValueError, match="unknown assembly family"):
        draw_assembly_variant("trebuchet", 0)


def test_variants_are_not_the_library_assemblies() -> None:
    """Other parameters than the library's five: more than one bolt, other casters and
    couplings (the library's bearing housing holds a bd_warehouse 608 bearing, which no
    variant uses)."""
    library = ("swivel caster wheel 75x25 axle 10 plate 80 sheet 3 race 8",
               "sleeve coupling 10x20x30,", "jaw coupling 40 bore 14 hub 16 jaws 12")
    for v in draw_assembly_variants(27 * 4, seed=1):
        assert not any(text in v.description for text in library), v.description
        if v.family == "bolted-joint":
            assert sum(p.startswith("bolt-") for p in v.parts) >= 2


def test_fastener_layout_sizes_are_the_built_parts() -> None:
    """The layouts stack bolts, washers and nuts by the tables; the built parts agree, and
    the bolt's shank has its nominal diameter (a concentric mate within 1 mm of the hole)."""
    for size in (SIZES[0], SIZES[3], SIZES[-1]):
        m = metric(size)
        nut_box, washer_box = nut(size).bounding_box(), washer(size).bounding_box()
        assert nut_box.size.Z == pytest.approx(m.nut_m, abs=1e-6)
        assert nut(size, thin=True).bounding_box().size.Z == pytest.approx(m.thin_m, abs=1e-6)
        assert washer_box.size.Z == pytest.approx(m.washer_h, abs=1e-6)
        assert washer_box.size.X == pytest.approx(m.washer_od, abs=1e-6)
        assert nut_box.size.X <= m.nut_e + 1e-6
        screw = bolt(size, 4 * m.d)
        assert screw.is_valid and screw.bounding_box().min.Z == pytest.approx(-4 * m.d)
        assert screw.bounding_box().size.X <= 2 * m.head_r + 1e-6
        radii = {round(f.radius, 6) for f in screw.faces() if f.geom_type == bd.GeomType.CYLINDER}
        assert m.d / 2 in radii


def test_overlaps_finds_shared_volume_and_ignores_contact() -> None:
    a = _box(10, 10, 10)
    touching, inside = bd.Pos(10, 0, 0) * _box(10, 10, 10), bd.Pos(8, 0, 0) * _box(10, 10, 10)
    a.label, touching.label, inside.label = "a", "touching", "inside"
    found = overlaps([a, touching, inside])
    assert [(x, y) for x, y, _ in found] == [("a", "inside"), ("touching", "inside")]
    assert found[0][2] == pytest.approx(2 * 10 * 10)


def test_missing_mates_reads_either_order_and_the_fit() -> None:
    table = pd.DataFrame({"name_a": ["shaft", "nut"], "name_b": ["collar", "plate"],
                          "relation": ["concentric", "coincident"], "fit": ["fit", None]})
    promised = [Mate("collar", "shaft", "concentric", "fit"),
                Mate("plate", "nut", "coincident"),
                Mate("collar", "shaft", "concentric", "clearance"),
                Mate("nut", "shaft", "coincident")]
    assert missing_mates(promised, table) == promised[2:]


@pytest.fixture(scope="module")
def audited(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The first variant of each family, written by two worker processes."""
    out = tmp_path_factory.mktemp("variants")
    write_assembly_variants(out, len(FAMILIES), AUDIT_SEED, workers=2)
    return out


@pytest.mark.parametrize("family", list(FAMILIES))
def test_parts_do_not_interfere_and_the_designed_mates_exist(family: str, audited: Path
                                                             ) -> None:
    v = draw_assembly_variant(family, 0, AUDIT_SEED)
    path = audited / f"{v.name}.step"
    solids = read_step(path)
    assert [s.info.name for s in solids] == list(v.parts)
    assert len({s.info.colour for s in solids}) == len(solids)  # every part its own colour
    shapes = [bd.Solid(s.shape) for s in solids]
    for shape, solid in zip(shapes, solids, strict=True):
        shape.label = solid.info.name
    assert overlaps(shapes) == []
    face = read_assembly_mates(path).level("face")
    assert missing_mates(v.mates, face) == []
    kinds = set(zip(face["relation"], face["fit"].fillna(""), strict=True))
    assert {("coincident", "")} <= kinds
    if family not in SLIDES:
        assert ("concentric", "fit") in kinds


def test_the_contact_families_slide_rest_and_turn_as_designed(tmp_path: Path) -> None:
    """Bars in grooves, carriages on rails and keys in keyways are sliders (planar contacts
    whose normals are not parallel) without interfering; their near misses are read as what
    they are: a loose carriage and a standard key's hub ride on one plane (planar), a hub
    turns on its shaft (cylindrical, or revolute against a shoulder). A segmented ring's
    neighbours are planar."""
    families = (*SLIDES, "segmented-ring")
    entries = write_assembly_variants(tmp_path, 4 * len(families), SLIDE_SEED,
                                      families=families)
    joints: dict[str, set[str]] = {}
    for e in entries:
        v = draw_assembly_variant(e.family, e.index, SLIDE_SEED)
        solids = read_step(tmp_path / e.path)
        shapes = [bd.Solid(s.shape) for s in solids]
        for shape, solid in zip(shapes, solids, strict=True):
            shape.label = solid.info.name
        assert overlaps(shapes) == [], e.name
        result = read_assembly_mates(tmp_path / e.path)
        assert missing_mates(v.mates, result.level("face")) == [], e.name
        for r in result.level("joint").itertuples():
            joints.setdefault(f"{v.family}:{r.name_a}-{r.name_b}", set()).add(str(r.kinematic))
    assert joints["slide-guide:base-bar"] == {"slider"}
    assert joints["rail-carriage:rail-carriage-1"] == {"slider", "planar"}  # fitted, loose
    assert joints["keyed-hub:shaft-key"] == {"slider"}
    assert joints["keyed-hub:hub-key"] == {"slider", "planar"}  # fitted, standard key
    assert joints["keyed-hub:shaft-hub"] == {"cylindrical", "revolute"}
    # a ring cut into segments: neighbours rest on their cuts, each turns on the shaft and in
    # its housing, and segments that are not neighbours have no joint
    assert joints["segmented-ring:segment-1-segment-2"] == {"planar"}
    assert joints["segmented-ring:segment-2-segment-3"] == {"planar"}
    assert "segmented-ring:segment-1-segment-3" not in joints
    assert joints["segmented-ring:shaft-segment-1"] == {"cylindrical", "revolute"}
    assert joints["segmented-ring:segment-1-housing"] == {"cylindrical"}


def test_an_open_ball_bearing_has_round_contacts_and_no_mate_of_its_balls_or_rings(
        audited: Path) -> None:
    """The family's point: balls touch both rings (a sphere in a groove, within 0.01 mm) and
    the rings share an axis, but neither makes a face mate; only the bore, the outside and
    the shoulder do."""
    v = draw_assembly_variant("ball-bearing", 0, AUDIT_SEED)
    balls = [p for p in v.parts if p.startswith("ball-")]
    assert len(balls) >= 5
    face = read_assembly_mates(audited / f"{v.name}.step").level("face")
    named = set(face["name_a"]) | set(face["name_b"])
    assert not named & set(balls)
    assert not face[face[["name_a", "name_b"]].isin(["inner-ring", "outer-ring"]).all(axis=1)
                    ].size
    solids = {s.info.name: bd.Solid(s.shape) for s in read_step(audited / f"{v.name}.step")}
    for ring in ("inner-ring", "outer-ring"):
        assert solids[balls[0]].distance_to(solids[ring]) < 0.01, ring


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[VariantEntry]]:
    """Three small variants written by two worker processes."""
    out = tmp_path_factory.mktemp("small") / "assemblies"
    return out, write_assembly_variants(out, 3, SMALL_SEED, families=SMALL, workers=2)


def test_same_seed_gives_byte_identical_files(small: tuple[Path, list[VariantEntry]],
                                              tmp_path: Path) -> None:
    """A fresh interpreter (another hash seed, building in-process) writes the same bytes; a
    rerun leaves every file alone; a corrupted file is rewritten and a smaller count removes
    the files no longer asked for."""
    out, entries = small
    assert [e.name for e in entries] == [f"{f}-v0000" for f in SMALL]
    bearings = draw_assembly_variant(SMALL[0], 0, SMALL_SEED).design.parts
    assert len({p.colour for p in bearings}) < len(bearings)  # OCCT shares their colour
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    assert write_assembly_variants(out, 3, SMALL_SEED, families=SMALL) == entries
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
    other = tmp_path / "again"
    code = ("import sys; from pathlib import Path; "
            "from cadio.samples.assembly_variants import write_assembly_variants; "
            "write_assembly_variants(Path(sys.argv[1]), 3, int(sys.argv[3]), "
            "families=sys.argv[2].split(','), workers=1)")
    env = {**os.environ, "PYTHONHASHSEED": "4321"}
    subprocess.run([sys.executable, "-c", code, str(other), ",".join(SMALL), str(SMALL_SEED)],
                   cwd=REPO, env=env, check=True, timeout=600)
    assert sorted(p.name for p in other.iterdir()) == sorted(before)
    for name in before:
        assert (other / name).read_bytes() == (out / name).read_bytes(), name
    (other / entries[0].path).write_text("garbage")
    assert write_assembly_variants(other, 2, SMALL_SEED, families=SMALL) == entries[:2]
    assert sorted(p.name for p in other.glob("*.step")) == sorted(e.path for e in entries[:2])
    assert (other / entries[0].path).read_bytes() == (out / entries[0].path).read_bytes()
    assert read_assembly_variants(other) == entries[:2]
    assert json.loads((other / VARIANTS_INDEX).read_text())["stamp"]["seed"] == SMALL_SEED


def test_ingest_and_the_mates_stage_find_every_part_and_the_designed_mates(
        small: tuple[Path, list[VariantEntry]], tmp_path: Path) -> None:
    out, entries = small
    ws = tmp_path / "ws"
    catalog = ingest(out, ws, IngestConfig(voxel_sizes=(32,), limits=Limits(workers=2)))
    ok = catalog[catalog["status"] == "ok"]
    assert len(ok) == len(catalog) == sum(len(e.parts) for e in entries)
    assert set(ok["category"]) == {"assemblies"}
    for e in entries:
        rows = ok[ok["source"] == str(out / e.path)].sort_values("solid_index")
        assert tuple(rows["name"]) == e.parts
    summaries = list(extract_assembly_mates(assembly_jobs(catalog, ws)))
    assert sorted(s.assembly for s in summaries if s.status == "ok") == sorted(
        e.name for e in entries)
    for e in entries:
        table = read_mates(Workspace(ws).mates(e.name))
        face = table[table["level"] == "face"]
        assert missing_mates([Mate(*m) for m in e.mates], face) == [], e.name
