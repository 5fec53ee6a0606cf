"""The nightly flow in this process, against the session's real Prefect server."""
# A real deployment run against a real local server is tested with the deployments.

from __future__ import annotations

import json
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from cadio.catalog import read_catalog
from cadio.tolerances import DEFAULT_TOLERANCES, read_tolerances
from reports.completion import read_completion_parts


@pytest.fixture(scope="module")
def harness(prefect_api: dict[str, str]) -> object:
    """This process's flows against the session's Prefect server (``prefect_api``): a
    temporary server of Prefect's test harness is a third server beside the two workers'."""
    from conftest import served_by

    with served_by(prefect_api):
        yield


def test_nightly_ingests_reports_and_caches(harness: object, tmp_path: Path,
                                            box_step: Path, pin_step: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    from flows.config import night_config
    from flows.nightly import nightly

    lib = tmp_path / "lib"
    (lib / "fasteners").mkdir(parents=True)
    (lib / "casters-wheels-trolleys").mkdir()
    shutil.copy(box_step, lib / "fasteners" / "box.step")
    shutil.copy(pin_step, lib / "fasteners" / "pin.step")
    (lib / "casters-wheels-trolleys" / "broken.stp").write_bytes(b"ISO-10303-21;\nHEADER;")
    ws = tmp_path / "ws"

    config = night_config({"library": {"path": str(lib), "voxel_sizes": [16], "batch_size": 1},
                           "runtime": {"workspace": str(ws)},
                           "capture": {"views_per_scene": 2, "pairs_per_relation": 1}})
    first = nightly(config)
    assert first.ingest.files == 3
    assert first.ingest.ok == 2 and first.ingest.failed == 1
    report = Path(first.ingest_report).read_text()
    assert "truncated STEP file" in report and "casters-wheels-trolleys" in report
    written = json.loads((Path(first.run_dir) / "ingest.json").read_text())
    assert written["totals"] == asdict(first.ingest)
    assert read_tolerances(Path(first.run_dir) / "tolerances.json") == DEFAULT_TOLERANCES

    stages = first.stages
    assert stages.scenes > 0 and stages.captures == stages.scenes
    assert stages.frames == 2 * stages.captures
    assert len(list((ws / "captures").glob("*.mcap"))) == stages.captures

    # every captured part completed by each method in both protocols, scored on its own
    parts = read_completion_parts(Path(first.run_dir))
    assert {"visible", "carve"} <= set(parts["method"])
    assert set(parts["protocol"]) == {"observed", "oracle-box"}
    assert parts["iou"].between(0, 1).all() and set(parts["n_views"]) >= {1, 2}
    assert "protocol: observed" in Path(first.completion_report).read_text()
    assert (ws / "runs" / "latest").resolve() == Path(first.run_dir)

    # every captured pair related in every view, by every method on every input
    pairs = pd.read_parquet(Path(first.run_dir) / "relations_pairs.parquet")
    assert set(pairs["method"]) == {"ltn", "mlp", "geometric"}
    assert set(pairs["input"]) == {"truth", "partial", "completed"}
    assert set(pairs["view"]) == {0, 1} and pairs["relation"].nunique() == 10
    learned = pairs[pairs["method"] != "geometric"]
    assert learned["confidence"].between(0.0, 1.0).all()
    summary = pd.read_csv(Path(first.run_dir) / "relations_summary.csv")
    assert {"all"} < set(summary["category"]) and summary["n"].gt(0).all()
    assert Path(first.relations_report).read_text().startswith("# Relations")

    meshes = sorted((ws / "meshes").glob("*.ply"))
    stamps = [m.stat().st_mtime_ns for m in meshes]
    replay = config.model_copy(update={"capture": config.capture.model_copy(
        update={"recordings": str(ws / "captures")})})
    second = nightly(replay)
    # unchanged files: the ingest tasks are cached on content hashes, nothing is rewritten
    assert second.ingest == first.ingest
    assert [m.stat().st_mtime_ns for m in meshes] == stamps and meshes
    assert len(read_catalog(ws / "catalog.parquet")) == 3
    # read back instead of rendered: same captures, same frames
    assert second.stages.captures == stages.captures
    assert second.stages.frames == stages.frames

    # the same recordings again: their related pair views are reused; under other pair
    # evidence code they are related anew
    related = sorted((ws / "relations").glob("*.parquet"))
    nightly(replay)
    assert related and sorted((ws / "relations").glob("*.parquet")) == related
    monkeypatch.setattr("flows.tasks.evidence_digest", lambda: "other evidence code")
    nightly(replay)
    assert set(related) < set((ws / "relations").glob("*.parquet"))


def _gap_assembly(path: Path, gap_mm: float) -> None:
    """A block standing ``gap_mm`` above a plate: a coincident mate only if gap <= contact."""
    import build123d as bd

    from cadio.cad.step import write_step

    plate = bd.Box(40, 40, 5, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
    block = bd.Pos(0, 0, 5 + gap_mm) * bd.Box(
        20, 20, 10, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
    plate.label, block.label = "plate", "block"
    write_step(bd.Compound(children=[plate, block], label="gap"), path)


def test_a_tolerance_set_on_the_cli_reaches_the_mates_of_the_run(
        harness: object, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from prefect.settings import PREFECT_API_URL

    from cadio.truth.mates import read_mates
    from flows.cli import main

    monkeypatch.setenv("PREFECT_API_URL", str(PREFECT_API_URL.value()))  # the session's server
    lib = tmp_path / "lib" / "assemblies"
    lib.mkdir(parents=True)
    _gap_assembly(lib / "gap.step", 0.2)

    def coincident(ws: Path, *tol: str) -> tuple[int, float]:
        args = ["nightly", "--library", str(lib.parent), "--workspace", str(ws),
                "--voxel-sizes", "16", "--views-per-scene", "1", "--no-inspection"]
        assert main(args + [a for t in tol for a in ("--tol", t)]) == 0
        table = read_mates(ws / "mates" / "gap.parquet")
        run = max((ws / "runs").iterdir())
        written = read_tolerances(run / "tolerances.json").as_dict()
        assert table.attrs["tolerances"] == written
        face = table[table["level"] == "face"]
        return int((face["relation"] == "coincident").sum()), written["contact_mm"]

    assert coincident(tmp_path / "default") == (0, DEFAULT_TOLERANCES.contact_mm)
    assert coincident(tmp_path / "loose", "contact_mm=0.3") == (1, 0.3)


def test_a_night_whose_recordings_are_all_unusable_fails_naming_them(
        harness: object, tmp_path: Path, box_step: Path, pin_step: Path,
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    from prefect.settings import PREFECT_API_URL

    from cadio.capture.scan import ScanConfig, capture_step
    from flows.cli import main
    from flows.config import ConfigError, night_config
    from flows.nightly import nightly

    lib = tmp_path / "lib" / "fasteners"
    lib.mkdir(parents=True)
    shutil.copy(box_step, lib / "box.step")
    recordings = tmp_path / "recordings"
    recordings.mkdir()
    other = capture_step(str(pin_step), tmp_path / "elsewhere", ScanConfig(views_per_scene=1))
    shutil.copy(other.path, recordings / "of-another-library.mcap")
    config = night_config({"library": {"path": str(lib.parent), "voxel_sizes": [16]},
                           "runtime": {"workspace": str(tmp_path / "ws")},
                           "capture": {"recordings": str(recordings)}})
    with pytest.raises(ConfigError, match=r"capture\.recordings: none of the 1 recording") as err:
        nightly(config)
    assert "of-another-library.mcap: shows parts that are not in the library" in str(err.value)
    assert not list((tmp_path / "ws").glob("runs/*/summary.json"))
    # the command line: the reason in one line, exit 2 as for a bad option, no traceback
    monkeypatch.setenv("PREFECT_API_URL", str(PREFECT_API_URL.value()))
    capsys.readouterr()
    assert main(["nightly", "--library", str(lib.parent), "--workspace", str(tmp_path / "ws"),
                 "--voxel-sizes", "16", "--captures", str(recordings)]) == 2
    out = capsys.readouterr()
    assert "of-another-library.mcap: shows parts that are not in the library" in out.err
    assert "Traceback" not in out.out + out.err
    # a recording of the library's own file (`mateqa capture FILE`) names its parts as ingest
    # does: beside the foreign one, the night scores it and reports the other
    ours = capture_step(str(lib / "box.step"), tmp_path / "here", ScanConfig(views_per_scene=1))
    shutil.copy(ours.path, recordings / "of-this-library.mcap")
    summary = nightly(config)
    stages = summary.stages
    assert (stages.captures, stages.captures_failed, stages.input_parts) == (2, 1, 1)
    assert summary.verdict == "UNCHECKED"  # one part, one file: too few to check, not a PASS


def _two_parts(tmp_path: Path, box_step: Path, pin_step: Path) -> Path:
    lib = tmp_path / "lib" / "fasteners"
    lib.mkdir(parents=True)
    shutil.copy(box_step, lib / "box.step")
    shutil.copy(pin_step, lib / "pin.step")
    return lib.parent


def _fill(example: Any) -> Any:
    """A toy completion: every voxel of the grid solid (module-level: the night's workers
    are handed it by reference)."""
    return np.ones_like(example.visible)


def _never(points: Any, *rest: Any) -> Any:
    """A toy relation method: no relation ever holds."""
    return np.zeros((len(points), 10), bool)


def test_a_method_registered_in_one_module_reaches_the_night_s_tables(
        harness: object, tmp_path: Path, box_step: Path, pin_step: Path) -> None:
    """A completion method and a relation method, each registered as its own module would
    register it, show in the night's completion and relation tables with no other edit (the
    stages' worker processes are handed them)."""
    from cadio.registry import Role
    from flows.config import night_config
    from flows.nightly import nightly
    from models.completions import COMPLETIONS, CompletionMethod
    from models.relation_methods import RELATION_METHODS, RelationMethod

    fill = CompletionMethod("fill", "every voxel of the grid solid", Role.BASELINE, 9,
                            __name__, solid=_fill)
    never = RelationMethod("never", "no relation ever holds", Role.BASELINE, 9, __name__,
                           decide=_never)
    config = night_config({"library": {"path": str(_two_parts(tmp_path, box_step, pin_step)),
                                      "voxel_sizes": [16]},
                           "runtime": {"workspace": str(tmp_path / "ws")},
                           "capture": {"views_per_scene": 1, "pairs_per_relation": 1},
                           "thresholds": {"fail_on_threshold": False}})
    with COMPLETIONS.registered(fill), RELATION_METHODS.registered(never):
        run = Path(nightly(config).run_dir)
    parts = read_completion_parts(run)
    filled = parts[parts["method"] == "fill"]
    assert len(filled) == len(parts[parts["method"] == "visible"]) > 0
    categories = pd.read_csv(run / "completion_categories.csv")
    assert "fill" in set(categories["method"])
    assert list(dict.fromkeys(categories["method"]))[-1] == "fill"  # after the registered ones
    pairs = pd.read_parquet(run / "relations_pairs.parquet")
    assert (~pairs[pairs["method"] == "never"]["predicted"]).all()
    assert set(pairs["input"][pairs["method"] == "never"]) == {"truth", "partial", "completed"}
    summary = pd.read_csv(run / "relations_summary.csv")
    assert "never" in set(summary["method"])
    assert "fill" not in COMPLETIONS and "never" not in RELATION_METHODS


def test_a_disk_full_during_the_captures_fails_the_night_and_the_next_captures_all(
        harness: object, tmp_path: Path, box_step: Path, pin_step: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    import errno
    import os

    from cadio.errors import MachineError
    from cadio.recordings.foxglove_mcap import CaptureWriter
    from flows.config import night_config
    from flows.nightly import nightly

    config = night_config({"library": {"path": str(_two_parts(tmp_path, box_step, pin_step)),
                                       "voxel_sizes": [16]},
                           "runtime": {"workspace": str(tmp_path / "ws")},
                           "capture": {"views_per_scene": 1, "pairs_per_relation": 1}})
    written = CaptureWriter.write_frame
    calls = []

    def every_other(self: CaptureWriter, frame: object) -> None:  # the disk fills, is freed...
        calls.append(self.path)
        if len(calls) % 2 == 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        written(self, frame)  # type: ignore[arg-type]

    monkeypatch.setattr(CaptureWriter, "write_frame", every_other)
    with pytest.raises(MachineError, match="No space left on device"):
        nightly(config)
    assert not list((tmp_path / "ws").glob("runs/*/summary.json"))  # no PASS of a broken night
    monkeypatch.undo()
    summary = nightly(config)  # the disk freed: nothing of the first night is kept as failed
    assert summary.stages.captures_failed == 0 and summary.stages.captures > 0
    assert set(read_catalog(tmp_path / "ws" / "catalog.parquet")["status"]) == {"ok"}


def test_a_night_stops_before_ingest_when_the_disk_cannot_hold_it(
        harness: object, tmp_path: Path, box_step: Path, pin_step: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    from collections import namedtuple

    from cadio.errors import DiskSpaceError
    from flows.config import night_config
    from flows.nightly import nightly

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 10**7, 10**7))
    config = night_config({"library": {"path": str(_two_parts(tmp_path, box_step, pin_step))},
                           "runtime": {"workspace": str(tmp_path / "ws")}})
    with pytest.raises(DiskSpaceError, match=r"10 MB free, but the 2 new STEP file\(s\) to "
                                             r"ingest need about 5\d MB"):
        nightly(config)
    assert not (tmp_path / "ws" / "catalog.parquet").exists()


def test_a_deployment_run_into_a_folder_that_is_no_workspace_fails_before_any_work(
        harness: object, tmp_path: Path, box_step: Path, pin_step: Path) -> None:
    """A night given someone's folder (a home, a project) as its workspace writes nothing
    there; ``/`` and the system folders are refused the same way (``test_workspace_claim``)."""
    from flows.config import ConfigError, night_config
    from flows.nightly import nightly

    home = tmp_path / "home"
    home.mkdir()
    (home / "notes.txt").write_text("mine")
    config = night_config({"library": {"path": str(_two_parts(tmp_path, box_step, pin_step))},
                           "runtime": {"workspace": str(home)}})
    with pytest.raises(ConfigError, match=r"runtime.workspace: .*home is not empty and not a "
                                          r"mateqa workspace \(it holds notes.txt\)"):
        nightly(config)
    assert [p.name for p in home.iterdir()] == ["notes.txt"]


def test_a_recording_in_an_assembly_s_folder_is_inspected_against_it(
        harness: object, tmp_path: Path) -> None:
    """`--captures DIR`: a recording in DIR/<assembly>/ (no masks, no scene, no part names)
    is checked as built against that assembly of the library; the learned route leaves it
    alone, and the night's as_built.csv holds it beside the assembly's own inspection."""
    import build123d as bd

    from cadio.cad.step import write_step
    from cadio.inspect.stage import InspectConfig, assembly_model, record
    from cadio.samples.assemblies import assembly_builders
    from cadio.workspace import Workspace
    from flows.config import night_config
    from flows.nightly import nightly

    name = "bolted-joint-m8"
    lib = tmp_path / "lib" / "fasteners"
    lib.mkdir(parents=True)
    build = {n: b for n, _, b in assembly_builders()}[name]
    write_step(bd.Compound(children=build(), label=name), lib / f"{name}.step")
    config = {"library": {"path": str(lib.parent), "voxel_sizes": [16]},
              "runtime": {"workspace": str(tmp_path / "ws")},
              "capture": {"views_per_scene": 1, "pairs_per_relation": 1},
              "inspection": {"views": 2, "parts_per_defect": 1},
              "thresholds": {"fail_on_threshold": False}}
    first = Path(nightly(night_config(config)).run_dir)  # the night's own inspection
    caught = pd.read_csv(first / "inspect_summary.csv").query("measure == 'caught'")
    assert set(caught["method"]) == {"registered", "design"}
    assert (caught.query("method == 'design'")["rate"] == 0).all()  # the design pose leaks none
    assert caught.query("method == 'registered'")["rate"].gt(0).any()  # and the scan some
    f1 = pd.read_csv(first / "registered_mates.csv")
    assert {"registered", "registered_cad", "truth"} <= set(f1["input"])
    # the workspace knows the assembly now: record it as built
    model = assembly_model(name, Workspace(tmp_path / "ws"))
    poses = dict(enumerate(model.design))
    lift = np.eye(4)
    lift[2, 3] = 5.0  # the upper plate 5 mm off the lower one
    poses[1] = lift @ poses[1]
    folder = tmp_path / "recordings" / name
    folder.mkdir(parents=True)
    record(model, poses, folder / "monday.mcap", InspectConfig(), instance_ids=False)
    summary = nightly(night_config({**config, "capture": {
        **config["capture"], "recordings": str(tmp_path / "recordings")}}))
    assert summary.stages.captures == 0  # the learned route did not read it
    as_built = pd.read_csv(Path(summary.run_dir) / "as_built.csv")
    mine = as_built[as_built["capture"] == f"{name}/monday.mcap"]
    assert not mine.empty and (mine["status"] == "broken").any()
    assert set(mine[mine["status"] == "broken"][["index_a", "index_b"]].stack()) >= {1}


def test_each_assembly_is_a_relation_batch_of_its_own_and_first() -> None:
    """An assembly holds most of a night's pair views: batched with others it kept one task
    busy while the other core idled."""
    from flows.tasks import relate_batches

    scenes = [Path(f"captures/s0-test-left-{i:05d}.mcap") for i in range(23)]
    whole = [Path("captures/assembly-gearbox.mcap"), Path("captures/assembly-press.mcap")]
    done = relate_batches(scenes[:12] + whole[:1] + scenes[12:] + whole[1:])
    assert done[:2] == [[whole[0]], [whole[1]]]
    assert all(1 <= len(b) <= 30 for b in done[2:])
    assert sorted(p for b in done for p in b) == sorted(scenes + whole)


def test_a_part_added_to_the_library_changes_its_own_batch_alone() -> None:
    """Batches cut where the items say, not where their count does: one scene more changes
    the batch it joins (or splits it), and every other batch stays as it was (a cache hit)."""
    from flows.tasks import stable_batches

    names = [f"s0-test-left-{i:05d}" for i in range(0, 400, 2)]
    before = stable_batches(names, 10)
    assert sorted(n for b in before for n in b) == names
    assert all(len(b) <= 30 for b in before) and 5 <= len(names) / len(before) <= 15
    for added in ("s0-test-left-00001", "s0-test-left-00199", "s0-test-left-00399"):
        after = stable_batches(sorted([*names, added]), 10)
        changed = [b for b in after if b not in before]
        assert 1 <= len(changed) <= 2 and any(added in b for b in changed)
        assert sum(len(b) for b in changed) <= 61


def test_the_costliest_assembly_is_inspected_first() -> None:
    """Two workers end together when the largest assembly starts first, not last."""
    from types import SimpleNamespace

    from flows.tasks import _largest_first

    catalog = pd.DataFrame({"source": ["small.step", "large.step", "large.step", "mid.step",
                                       "mid.step", "small.step"],
                            "bbox_min": [[0.0, 0, 0]] * 4 + [[], None],
                            "bbox_max": [[10.0, 0, 0], [300.0, 0, 0], [200.0, 0, 0],
                                         [400.0, 0, 0], [], None]})  # two failed solids
    mates = [SimpleNamespace(source=s) for s in ("small.step", "mid.step", "large.step")]
    order = _largest_first(mates, catalog)  # type: ignore[arg-type]
    assert [m.source for m in order] == ["large.step", "mid.step", "small.step"]
