"""Every part of the library scored once: the scoring plan, parts captured alone, examples built
only where a part is scored, and the coverage of the completion report, on real STEP files."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cadio.cad.ingest import IngestConfig, ingest
from cadio.capture.coverage import (
    alone_id,
    capture_context,
    capture_parts_alone,
    ingested_parts,
    placements,
    scoring_plan,
    unscored_parts,
)
from cadio.capture.scan import ASSEMBLY_PREFIX, ScanConfig, capture_assembly, capture_batch
from cadio.catalog import read_catalog
from cadio.contracts import CaptureSummary
from cadio.sandbox import Limits
from cadio.truth.assemblies import assembly_jobs, mates_job
from cadio.truth.scene_config import SceneConfig
from cadio.truth.scenes import generate_scenes, read_scene_parts, write_scenes
from cadio.workspace import Workspace

# Two views and pairs of them: the shipped completion checkpoints read 32^3 and write 64^3.
CFG = ScanConfig(views_per_scene=2, lengths=(2,))
LIBRARY = {
    "fasteners": ["fasteners/kcl_washer.step", "fasteners/kcl_hex-nut.step"],
    "couplings": ["brakes-clutches-couplings/spot_Shaft_Coupling.step"],
    "assemblies": ["assemblies/abc_00009776_handwheel.step"],
}


def test_each_part_is_scored_in_the_first_capture_of_each_context_that_places_it() -> None:
    plan = scoring_plan({"s2": ["b", "c"], "s1": ["a", "b"], "assembly-x": ["d", "a"],
                         "s3": ["c", "b"], "assembly-w": ["e"], "alone-f": ["f"]})
    assert plan == {"alone-f": ("f",), "assembly-w": ("e",), "assembly-x": ("a", "d"),
                    "s1": ("a", "b"), "s2": ("c",)}
    assert scoring_plan({}) == {}
    assert [capture_context(c) for c in ("s0-test-left-00001", "assembly-x", "alone-f")] == [
        "pair", "assembly", "alone"]


@dataclass(frozen=True)
class Night:
    """The capture side of a night on a small real library, run by the stage functions."""

    ws: Workspace
    catalog: pd.DataFrame
    scenes: pd.DataFrame
    plan: dict[str, tuple[str, ...]]
    captured: list[CaptureSummary]
    alone: list[str]


@pytest.fixture(scope="module")
def night(shared_step_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Night:
    """Washer and nut in three pair scenes, the coupling in none (the scenes offer it no
    partner), the handwheel captured as placed; then every part nothing scored, alone."""
    lib = tmp_path_factory.mktemp("lib")
    for category, names in LIBRARY.items():
        (lib / category).mkdir()
        for name in names:
            shutil.copy(shared_step_dir / name, lib / category / Path(name).name)
    ws = Workspace(tmp_path_factory.mktemp("ws"))
    ingest(lib, ws.root, IngestConfig(voxel_sizes=(32,), limits=Limits(workers=1)))
    catalog = read_catalog(ws.catalog)
    fasteners = [p for p in read_scene_parts(catalog, ws.root) if p.category == "fasteners"]
    scenes = generate_scenes(fasteners, SceneConfig(pairs_per_relation=1, val_fraction=0.0,
                                                    test_fraction=0.0)).head(3)
    write_scenes(ws.scenes, scenes)
    jobs = assembly_jobs(catalog, ws.root)
    assert all(mates_job(j).ok for j in jobs)
    plan = scoring_plan(placements(scenes, jobs))
    captured = capture_batch(scenes["scene_id"].tolist(), ws, CFG, plan)
    captured += [capture_assembly(j.assembly, j.category, list(j.part_ids.values()), ws, CFG,
                                  plan.get(ASSEMBLY_PREFIX + j.assembly, ())) for j in jobs]
    alone = unscored_parts(catalog, captured)
    captured += capture_parts_alone(alone, ws, CFG)
    return Night(ws, catalog, scenes, plan, captured, alone)


def _part(catalog: pd.DataFrame, source: str) -> str:
    return str(catalog.loc[catalog["source"].str.endswith(source), "part_id"].iloc[0])


def test_a_part_in_no_scene_is_captured_and_scored_alone(night: Night) -> None:
    coupling = _part(night.catalog, "spot_Shaft_Coupling.step")
    placed = {p for parts in placements(night.scenes, []).values() for p in parts}
    assert coupling not in placed and coupling in night.alone
    alone = next(c for c in night.captured if c.scene_id == alone_id(coupling))
    assert alone.error == "" and alone.frames == 2 and alone.scored == (coupling,)
    folder = night.ws.inputs(alone_id(coupling), 1)
    names = {p.stem for p in folder.glob("*-*.npz")}
    assert {"observed-0", "oracle-box-0"} <= names and any(n.count("-") > 2 for n in names)
    assert unscored_parts(night.catalog, night.captured) == []


def test_every_ingested_part_is_scored_exactly_once(night: Night) -> None:
    scored = [pid for c in night.captured if not c.error for pid in c.scored]
    assert sorted(scored) == sorted(ingested_parts(night.catalog)["part_id"])
    first_scene = str(night.scenes["scene_id"].min())
    washer, nut = (_part(night.catalog, n) for n in ("kcl_washer.step", "kcl_hex-nut.step"))
    by_capture = {c.scene_id: set(c.scored) for c in night.captured}
    assert by_capture[first_scene] == {washer, nut}
    later = [s for s in night.scenes["scene_id"] if s != first_scene]
    assert later and all(by_capture[s] == set() for s in later)
    # a part of the handwheel is scored where it is placed, or alone when no view shows it
    for pid in night.plan[f"{ASSEMBLY_PREFIX}abc_00009776_handwheel"]:
        assert pid in by_capture[f"{ASSEMBLY_PREFIX}abc_00009776_handwheel"] or pid in night.alone


def _meta(path: Path) -> dict[str, object]:
    with np.load(path) as z:
        return dict(json.loads(str(z["meta"])), has_target="target" in z)


def test_learning_examples_are_built_only_where_a_part_is_scored(night: Night) -> None:
    """A part a capture does not score gets its points and, per view, only the observed input
    the relation stage completes: no target, no baselines, no sequence, no oracle-box."""
    scored = {(c.scene_id, pid) for c in night.captured for pid in c.scored}
    folders = [f for f in (night.ws.root / "inputs").glob("*/*") if f.is_dir()]
    metas = {f: [_meta(p) for p in sorted(f.glob("*-*.npz"))] for f in folders}
    shown = {f: (f.parent.name, str(m[0]["part_id"])) for f, m in metas.items() if m}
    assert len(shown) == len(folders) and set(shown.values()) >= scored
    assert len(folders) > len(scored)  # some parts are shown where they are not scored
    for folder in folders:
        assert (folder / "points.npz").is_file()
        if shown[folder] in scored:
            assert all(m["has_target"] for m in metas[folder])
            assert {m["protocol"] for m in metas[folder]} == {"observed", "oracle-box"}
        else:
            assert all(not m["has_target"] and m["input_only"] for m in metas[folder])
            assert {m["protocol"] for m in metas[folder]} == {"observed"}
            assert all(len(m["views"]) == 1 for m in metas[folder])  # type: ignore[arg-type]


def test_the_completion_report_counts_every_part_of_the_library(night: Night,
                                                                tmp_path: Path) -> None:
    from models.evaluate import SHIPPED, complete_isolated, part_inputs, write_completion_report
    from reports.completion import read_completion_parts
    from reports.coverage import read_part_coverage

    inputs = night.ws.root / "inputs"
    folders = part_inputs([inputs / c.scene_id for c in night.captured if not c.error])
    assert len(folders) == len(ingested_parts(night.catalog))  # one context each here
    scores = complete_isolated(folders, SHIPPED, night.ws)  # as the night: in a worker
    assert scores.failed == []
    write_completion_report(tmp_path, [scores], ingested_parts(night.catalog))
    coverage = read_part_coverage(tmp_path).set_index("category")
    handwheel = int((night.catalog["source"].str.endswith("handwheel.step")
                     & (night.catalog["status"] == "ok")).sum())
    assert coverage["parts_ingested"].to_dict() == {
        "assemblies": handwheel, "couplings": 1, "fasteners": 2, "all": handwheel + 3}
    assert (coverage["parts_scored"] == coverage["parts_ingested"]).all()
    assert (coverage["coverage_parts"] == 1.0).all()
    parts = read_completion_parts(tmp_path)
    assert set(parts["part_id"]) == set(ingested_parts(night.catalog)["part_id"])
    # the library's CAD registered in each view (no pose given) fills the cube better than
    # any learned completion, on every example the others complete
    observed = parts[parts["protocol"] == "observed"]
    iou = observed.groupby("method")["iou"].mean()
    per_method = observed.groupby("method").size()
    assert per_method["registered"] == per_method["gan_lstm"]
    assert iou["registered"] > 0.8 and iou["registered"] > iou["gan_lstm"] + 0.2


def test_no_pose_of_the_scene_reaches_the_registered_completion(
        night: Night, monkeypatch: pytest.MonkeyPatch) -> None:
    """Scrambling every part's pose in the scene meta the registered completion reads (for
    its bill of materials and scale) leaves each solid as it was."""
    import cadio.inspect.completion as completion
    from cadio.capture.examples import read_example
    from models.evaluate import part_inputs

    inputs = night.ws.root / "inputs"
    folders = part_inputs([inputs / c.scene_id for c in night.captured if not c.error])
    examples = [read_example(sorted(f.glob("observed-*.npz"))[0]) for f in folders][:4]
    read = completion.read_scene_meta

    def solids() -> list[np.ndarray]:
        return [completion.registered_solid(e, completion.capture_cad(
            night.ws.capture(str(e.meta["capture"])), night.ws)) for e in examples]

    def scrambled(path: Path) -> dict[str, object] | None:
        meta = read(path)
        rng = np.random.default_rng(0)
        for part in (meta or {}).get("parts", []):
            pose = np.eye(4)
            pose[:3, 3] = rng.uniform(-500, 500, 3)
            part["pose_mm"] = pose.tolist()
        return meta

    honest = solids()
    monkeypatch.setattr(completion, "read_scene_meta", scrambled)
    blind = solids()
    assert len(examples) == 4 and all(a.any() for a in honest)
    assert all(np.array_equal(a, b) for a, b in zip(honest, blind, strict=True))


def test_a_completion_worker_that_dies_fails_its_folders_not_the_night(night: Night) -> None:
    from models.evaluate import SHIPPED, complete_isolated, part_inputs

    inputs = night.ws.root / "inputs"
    folders = part_inputs([inputs / c.scene_id for c in night.captured if not c.error])[:2]
    scores = complete_isolated(folders, SHIPPED, night.ws, Limits(seconds=0.5, workers=1))
    assert scores.parts == [] and [f for f, _ in scores.failed] == [str(f) for f in folders]
    assert all("completion worker" in why and "time" in why for _, why in scores.failed)
