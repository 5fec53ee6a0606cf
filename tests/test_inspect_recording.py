"""``mateqa inspect ASSEMBLY.step RECORDING.mcap`` on recordings written as a RealSense driver
writes them: real size, the D435's noise, a table, no masks, no scene, no part names."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from cadio.cad.step import write_step
from cadio.inspect.asbuilt import BROKEN
from cadio.inspect.recording import AS_BUILT_FIELDS, prepare_design
from cadio.inspect.routes import AssemblyModel
from cadio.inspect.stage import InspectConfig, assembly_model, record
from cadio.inspect.surface import part_surface
from cadio.inspect.symmetry import symmetry_of
from cadio.recordings.mcap_io import read_capture, read_scene_meta
from cadio.workspace import Workspace
from flows.cli import main

ASSEMBLY = "bolted-joint-m8"
CAMERA = InspectConfig()  # the night's inspection camera: 4 views, a D435 at 0.6 m


@pytest.fixture(scope="module")
def design(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Workspace, AssemblyModel]:
    import build123d as bd

    from cadio.samples.assemblies import assembly_builders

    build = {name: b for name, _, b in assembly_builders()}[ASSEMBLY]
    step = tmp_path_factory.mktemp("cad") / f"{ASSEMBLY}.step"
    write_step(bd.Compound(children=build(), label=ASSEMBLY), step)
    ws = Workspace(tmp_path_factory.mktemp("ws"))
    prepare_design(step, ws)
    return step, ws, assembly_model(ASSEMBLY, ws)


def _inspect(step: Path, recording: Path, ws: Workspace, out: Path,
             capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(["inspect", str(step), str(recording), "--workspace", str(ws.root), "--out",
                 str(out)])
    printed = capsys.readouterr()
    return code, printed.out, printed.err


def test_a_recording_of_the_assembly_as_designed_holds(
        design: tuple[Path, Workspace, AssemblyModel], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    step, ws, model = design
    recording = record(model, dict(enumerate(model.design)), tmp_path / "intact.mcap", CAMERA,
                       instance_ids=False)
    assert read_scene_meta(recording) is None
    assert all(f.instance is None for f in read_capture(recording))
    code, out, err = _inspect(step, recording, ws, tmp_path / "as_built.csv", capsys)
    assert code == 0, out + err
    assert f"{ASSEMBLY}: HOLDS" in out
    with (tmp_path / "as_built.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert rows and tuple(rows[0]) == AS_BUILT_FIELDS
    assert {r["relation"] for r in rows} <= {"concentric", "coincident"}
    assert not [r for r in rows if r["status"] == BROKEN]
    assert any(r["status"] == "holds" for r in rows)


def test_a_lifted_plate_is_a_broken_mate_and_exit_3(
        design: tuple[Path, Workspace, AssemblyModel], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    step, ws, model = design
    upper = 1  # the upper plate, lifted 5 mm off the lower one
    poses = dict(enumerate(model.design))
    lift = np.eye(4)
    lift[2, 3] = 5.0
    poses[upper] = lift @ poses[upper]
    recording = record(model, poses, tmp_path / "lifted.mcap", CAMERA, instance_ids=False)
    code, out, err = _inspect(step, recording, ws, tmp_path / "as_built.csv", capsys)
    assert code == 3, out + err
    assert "broken" in out
    with (tmp_path / "as_built.csv").open() as fh:
        broken = [r for r in csv.DictReader(fh) if r["status"] == BROKEN]
    assert broken and all(str(upper) in (r["index_a"], r["index_b"]) for r in broken)


def test_a_recording_of_something_else_is_a_clear_answer(
        design: tuple[Path, Workspace, AssemblyModel], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    from tests.test_inspect import _box_mesh

    step, ws, _ = design
    box = part_surface("box", _box_mesh(90, 70, 45))
    other = AssemblyModel("other", (box,), (np.eye(4),), (symmetry_of(box.samples),),
                          ("box",))
    recording = record(other, {0: np.eye(4)}, tmp_path / "other.mcap", CAMERA,
                       instance_ids=False)
    code, _, err = _inspect(step, recording, ws, tmp_path / "as_built.csv", capsys)
    assert code == 2
    assert str(recording) in err and f"does not show {ASSEMBLY}" in err
    assert not (tmp_path / "as_built.csv").exists()


def test_a_file_that_is_no_recording_is_bad_input(
        design: tuple[Path, Workspace, AssemblyModel], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    step, ws, _ = design
    bad = tmp_path / "notes.mcap"
    bad.write_text("not a recording")
    code, _, err = _inspect(step, bad, ws, tmp_path / "as_built.csv", capsys)
    assert code == 2 and str(bad) in err
