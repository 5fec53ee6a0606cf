"""Tests of the generated sample library: counts, read-back, assemblies, determinism."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import build123d as bd
import numpy as np
import pytest

from cadio.records import Category
from cadio.samples.library import (
    ASSEMBLIES,
    LIBRARY_INDEX,
    LibraryEntry,
    SampleConfig,
    generate_library,
    read_library,
)
from cadio.tolerances import DEFAULT_TOLERANCES as TOL

REPO = Path(__file__).resolve().parents[1]
EXPECTED_PARTS = {
    "bolted-joint-m8": ("plate-lower", "plate-upper", "bolt", "washer", "nut"),
    "bearing-housing-608": ("housing", "bearing", "shaft"),
    "swivel-caster-d75": ("plate", "fork", "axle", "wheel"),
    "sleeve-coupling-d10": ("sleeve", "shaft-a", "shaft-b"),
    "jaw-coupling-d40": ("hub-a", "spider", "hub-b", "shaft-a", "shaft-b"),
}


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path]]:
    out = tmp_path_factory.mktemp("library")
    return out, generate_library(out)


@pytest.fixture(scope="module")
def entries(library: tuple[Path, list[Path]]) -> dict[str, LibraryEntry]:
    return {e.path: e for e in read_library(library[0])}


def _children(path: Path) -> dict[str, bd.Shape]:
    shape = bd.import_step(path)
    return {child.label: child for child in shape.children}


def _main_axis(shape: bd.Shape) -> bd.Axis:
    """Axis of the largest cylindrical face (the shank, the bore, the outer ring)."""
    cylinders = [f for f in shape.faces() if f.geom_type == bd.GeomType.CYLINDER]
    return max(cylinders, key=lambda f: f.area).axis_of_rotation


def _assert_coaxial(a: bd.Axis, b: bd.Axis) -> None:
    da, db = np.array(tuple(a.direction)), np.array(tuple(b.direction))
    angle = np.degrees(np.arccos(min(1.0, abs(float(da @ db)))))
    offset = np.array(tuple(b.position - a.position))
    distance = np.linalg.norm(offset - (offset @ da) * da)
    assert angle <= TOL.coaxial_deg and distance <= TOL.coaxial_mm, (angle, distance)


def test_generation_is_complete(library, entries) -> None:
    out, paths = library
    assert paths == sorted(paths)
    assert {out / p for p in entries} == set(paths)
    for category in Category.paper():
        assert len(list((out / category).glob("*.step"))) >= 10, category
    assert {e.name for e in entries.values() if e.category == ASSEMBLIES} >= set(EXPECTED_PARTS)
    assert all(e.description and e.n_solids >= 1 for e in entries.values())


def test_every_file_reads_back_with_valid_solids(library, entries) -> None:
    out = library[0]
    for rel, entry in entries.items():
        solids = bd.import_step(out / rel).solids()
        assert len(solids) == entry.n_solids, rel
        assert all(s.is_valid and s.volume > 0 for s in solids), rel
        if entry.category != ASSEMBLIES:
            assert entry.n_solids == 1 and entry.parts == (entry.name,), rel


def test_assemblies_have_named_coloured_parts(library) -> None:
    out = library[0]
    for name, parts in EXPECTED_PARTS.items():
        children = _children(out / ASSEMBLIES / f"{name}.step")
        assert tuple(children) == parts, name
        colours = {tuple(round(c, 3) for c in child.color) for child in children.values()}
        assert None not in colours and len(colours) == len(parts), name
        assert all(len(child.solids()) == 1 for child in children.values()), name


def test_assembly_parts_touch_but_do_not_interfere(library) -> None:
    """Parts are in contact (the contact graph is connected) and no two overlap in volume."""
    out = library[0]
    for name in EXPECTED_PARTS:
        parts = {k: c.solids()[0] for k, c in _children(out / ASSEMBLIES / f"{name}.step").items()}
        reached, frontier = {next(iter(parts))}, [next(iter(parts))]
        while frontier:
            here = frontier.pop()
            for other in parts.keys() - reached:
                if parts[here].distance_to(parts[other]) <= TOL.contact_mm:
                    reached.add(other)
                    frontier.append(other)
        assert reached == set(parts), name
        for a, b in itertools.combinations(parts.values(), 2):
            common = a.intersect(b)
            assert common is None or sum(s.volume for s in common.solids()) < 1e-3, name


def test_bolted_joint_is_coaxial_and_stacked(library) -> None:
    parts = _children(library[0] / ASSEMBLIES / "bolted-joint-m8.step")
    bolt_axis = _main_axis(parts["bolt"])
    for other in ("nut", "washer", "plate-lower", "plate-upper"):
        _assert_coaxial(bolt_axis, _main_axis(parts[other]))
    box = {k: v.bounding_box() for k, v in parts.items()}
    assert box["plate-lower"].max.Z == pytest.approx(box["plate-upper"].min.Z, abs=1e-6)
    assert box["washer"].max.Z == pytest.approx(box["plate-lower"].min.Z, abs=1e-6)
    assert box["nut"].max.Z == pytest.approx(box["washer"].min.Z, abs=1e-6)
    assert box["bolt"].min.Z < box["nut"].min.Z  # the bolt comes out of the nut


def test_shaft_lines_are_coaxial(library) -> None:
    out = library[0]
    housing = _children(out / ASSEMBLIES / "bearing-housing-608.step")
    _assert_coaxial(_main_axis(housing["bearing"]), _main_axis(housing["housing"]))
    _assert_coaxial(_main_axis(housing["bearing"]), _main_axis(housing["shaft"]))
    for name in ("sleeve-coupling-d10", "jaw-coupling-d40"):
        parts = _children(out / ASSEMBLIES / f"{name}.step")
        _assert_coaxial(_main_axis(parts["shaft-a"]), _main_axis(parts["shaft-b"]))
    caster = _children(out / ASSEMBLIES / "swivel-caster-d75.step")
    _assert_coaxial(_main_axis(caster["axle"]), _main_axis(caster["wheel"]))


def test_second_call_leaves_files_alone(library) -> None:
    out, paths = library
    before = [p.stat().st_mtime_ns for p in paths]
    index = (out / LIBRARY_INDEX).stat().st_mtime_ns
    assert generate_library(out) == paths
    assert [p.stat().st_mtime_ns for p in paths] == before
    assert (out / LIBRARY_INDEX).stat().st_mtime_ns == index
    stamp = json.loads((out / LIBRARY_INDEX).read_text())["stamp"]
    assert stamp["config"] == {"step_timestamp": SampleConfig().step_timestamp, "gears": True,
                               "variants": 0, "variant_seed": 0}


def test_generation_is_deterministic_across_processes(library, tmp_path) -> None:
    """A second generation in a fresh interpreter (other hash seed) gives identical bytes;
    on the way it repairs a corrupted file and removes a file the old index listed."""
    out, paths = library
    stale = tmp_path / Category.FASTENERS.value / "retired-part.step"
    corrupt = tmp_path / Category.FASTENERS.value / "hex-nut-m8.step"
    stale.parent.mkdir()
    stale.write_text("old")
    corrupt.write_text("garbage")
    old_entry = {"path": stale.relative_to(tmp_path).as_posix(), "sha256": "0"}
    old_index = {"stamp": {"version": 0}, "files": [old_entry]}
    (tmp_path / LIBRARY_INDEX).write_text(json.dumps(old_index))
    code = "import sys; from pathlib import Path; "
    code += "from cadio.samples.library import generate_library; "
    code += "generate_library(Path(sys.argv[1]))"
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    subprocess.run([sys.executable, "-c", code, str(tmp_path)], cwd=REPO, env=env, check=True,
                   timeout=300)
    assert not stale.exists()
    for path in [*paths, out / LIBRARY_INDEX]:
        other = tmp_path / path.relative_to(out)
        assert other.read_bytes() == path.read_bytes(), path.relative_to(out)


def test_variants_are_seeded_distinct_and_valid() -> None:
    from cadio.samples.variants import draw_variants

    first, again = draw_variants(3, seed=5), draw_variants(3, seed=5)
    assert [v.description for v in first] == [v.description for v in again]
    assert [v.description for v in first] != [v.description for v in draw_variants(3, seed=6)]
    assert len({(v.category, v.name) for v in first}) == len(first) == 12
    assert {v.category for v in first} == set(Category.paper())
    for v in first[::3]:  # one of each category builds into one valid, labelled solid
        solid = v.build()
        assert solid.is_valid and solid.volume > 0 and solid.label == v.name
