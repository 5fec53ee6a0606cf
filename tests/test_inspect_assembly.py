"""The inspection of a whole assembly: captured at real size, registered, its mates checked, its
planted defects caught; nothing of the answer reaching the capture or the search route."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cadio.cad.ingest import IngestConfig, ingest
from cadio.cad.step import write_step
from cadio.catalog import read_catalog
from cadio.inspect.asbuilt import BROKEN, HOLDS, NOT_INSPECTABLE
from cadio.inspect.defects import Defect, DefectPlan, Variant
from cadio.inspect.evaluate import DESIGN, REGISTERED, inspect_assembly, read_tables
from cadio.inspect.routes import AssemblyModel, Found, by_search
from cadio.inspect.scan import scan_of
from cadio.inspect.stage import (
    InspectConfig,
    assembly_model,
    capture_variant,
    inspect_capture,
    read_truth,
    scored_as,
)
from cadio.inspect.symmetry import pose_error
from cadio.recordings.mcap_io import read_capture, read_scene_meta
from cadio.sandbox import Limits
from cadio.truth.assemblies import assembly_jobs, mates_job
from cadio.workspace import Workspace

ASSEMBLY = "bolted-joint-m8"
QUIET = InspectConfig(views=2, near_m=None, noise=False,
                      defects=DefectPlan(shifts_mm=(), turns_deg=(), missing=False), search=False)


@pytest.fixture(scope="module")
def ws(tmp_path_factory: pytest.TempPathFactory) -> Workspace:
    """A workspace holding the sample library's bolted joint (two plates, bolt, washer, nut),
    ingested, with its mates."""
    import build123d as bd

    from cadio.samples.assemblies import assembly_builders

    build = {name: b for name, _, b in assembly_builders()}[ASSEMBLY]
    lib = tmp_path_factory.mktemp("lib")
    (lib / "assemblies").mkdir()
    write_step(bd.Compound(children=build(), label=ASSEMBLY), lib / "assemblies" /
               f"{ASSEMBLY}.step")
    space = Workspace(tmp_path_factory.mktemp("ws"))
    ingest(lib, space.root, IngestConfig(voxel_sizes=(32,), limits=Limits(workers=2)))
    for job in assembly_jobs(read_catalog(space.catalog), space.root):
        assert mates_job(job).status == "ok"
    return space


@pytest.fixture(scope="module")
def model(ws: Workspace) -> AssemblyModel:
    return assembly_model(ASSEMBLY, ws)


def _mates(ws: Workspace) -> pd.DataFrame:
    return pd.read_parquet(ws.mates(ASSEMBLY))


def test_a_capture_for_inspection_carries_no_scene_and_no_part_names(
        ws: Workspace, model: AssemblyModel) -> None:
    path = capture_variant(model, Variant(ASSEMBLY, "intact"), ws, QUIET)
    assert read_scene_meta(path) is None
    raw = path.read_bytes()
    for part in model.parts:
        assert part.part_id.encode() not in raw
    frames = list(read_capture(path))
    assert len(frames) == QUIET.views
    # real size: the plates' 60 mm span some hundred pixels at 0.6 m, not the whole image
    depth = frames[0].depth[np.isfinite(frames[0].depth) & (frames[0].depth > 0)]
    assert 0.45 < float(np.median(depth)) < 0.75


def test_near_views_follow_the_views_around_at_their_own_distance(
        ws: Workspace, model: AssemblyModel) -> None:
    near = replace(QUIET, near_m=0.3)
    path = capture_variant(model, Variant(ASSEMBLY, "intact"), ws, near)
    frames = list(read_capture(path))
    assert len(frames) == 2 * QUIET.views and len({f.timestamp_ns for f in frames}) == 4
    eyes = [np.linalg.inv(f.world_to_camera)[:3, 3] for f in frames]
    around, nearer = eyes[:QUIET.views], eyes[QUIET.views:]
    for far, close in zip(around, nearer, strict=True):  # the same turn, twice as near
        centre = far - (far - close) * 0.6 / 0.3
        assert np.linalg.norm(far - centre) == pytest.approx(0.6, rel=1e-6)
        assert np.linalg.norm(close - centre) == pytest.approx(0.3, rel=1e-6)
    depth = frames[-1].depth[np.isfinite(frames[-1].depth) & (frames[-1].depth > 0)]
    assert 0.2 < float(np.median(depth)) < 0.4


def test_noise_free_the_design_route_places_every_seen_part_exactly(
        ws: Workspace, model: AssemblyModel) -> None:
    path = capture_variant(model, Variant(ASSEMBLY, "intact"), ws, QUIET)
    truth = read_truth(ws, path.stem)
    inspected = inspect_capture(model, path, _mates(ws), QUIET, fixture=np.eye(4))[0]
    placed = {i: p for i, p in inspected.parts.items() if p.pose is not None}
    # the cameras look down on the plates: the washer and nut under them are hidden, which
    # the design says (not inspectable), where a part the design shows and the scan lacks
    # would be missing
    hidden = {i for i, p in inspected.parts.items() if p.pose is None}
    assert len(placed) == 3 and len(hidden) == 2
    assert all(inspected.parts[i].problem.startswith("too little") for i in hidden)
    assert all(m.status == NOT_INSPECTABLE for m in inspected.mates
               if {m.index_a, m.index_b} & hidden)
    for i, part in placed.items():
        mm, deg = pose_error(part.pose, np.array(truth["poses"][str(i)]),  # type: ignore[arg-type]
                             model.symmetries[i])
        assert mm < 0.05 and deg < 0.05, (i, mm, deg)
    assert inspected.mates and all(m.status != BROKEN for m in inspected.mates)
    assert any(m.status == HOLDS for m in inspected.mates)


def test_a_shifted_part_is_caught_and_the_design_baseline_catches_nothing(
        ws: Workspace, model: AssemblyModel) -> None:
    mates = _mates(ws)
    face = mates[(mates["level"] == "face") & (mates["relation"] == "coincident")]
    row = face.iloc[0]
    moved = int(row["index_a"])
    normal = np.array(row["axis"], dtype=np.float64)
    defect = Defect(moved, "shift", 5.0, tuple(normal / np.linalg.norm(normal)))  # type: ignore[arg-type]
    path = capture_variant(model, Variant(ASSEMBLY, "shift-test", (defect,)), ws, QUIET)
    inspected = inspect_capture(model, path, mates, QUIET, fixture=np.eye(4))[0]
    broken = [m for m in inspected.mates if m.status == BROKEN]
    assert broken and all(moved in (m.index_a, m.index_b) for m in broken)
    assert not [m for m in inspected.baseline if m.status == BROKEN]
    missing = Defect(moved, "missing", 0.0)
    path = capture_variant(model, Variant(ASSEMBLY, "missing-test", (missing,)), ws, QUIET)
    inspected = inspect_capture(model, path, mates, QUIET, fixture=np.eye(4))[0]
    assert inspected.parts[moved].problem == "missing"
    assert any(m.status == BROKEN for m in inspected.mates if moved in (m.index_a, m.index_b))


def test_a_part_the_depth_sees_through_is_missing_however_few_points_the_design_shows(
        ws: Workspace, model: AssemblyModel) -> None:
    """With the points a missing call needs above what the design shows of any part, a part
    left out is still missing where the camera sees through nearly all of its place, and
    "too little of it seen" without that rule; of the intact assembly, none is missing."""
    mates = _mates(ws)
    face = mates[(mates["level"] == "face") & (mates["relation"] == "coincident")]
    gone = int(face.iloc[0]["index_a"])
    few = replace(QUIET, route=replace(QUIET.route, missing_min_points=10**9))
    path = capture_variant(model, Variant(ASSEMBLY, "missing-test", (
        Defect(gone, "missing", 0.0),)), ws, QUIET)
    assert inspect_capture(model, path, mates, few, fixture=np.eye(4))[0] \
        .parts[gone].problem == "missing"
    unsure = replace(few, route=replace(few.route, absent_sure=0.0))
    assert inspect_capture(model, path, mates, unsure, fixture=np.eye(4))[0] \
        .parts[gone].problem == "too little of it seen"
    intact = capture_variant(model, Variant(ASSEMBLY, "intact"), ws, QUIET)
    parts = inspect_capture(model, intact, mates, few, fixture=np.eye(4))[0].parts
    assert not [i for i, p in parts.items() if p.problem == "missing"]


def test_a_part_the_depth_agrees_with_where_it_stands_is_not_missing_for_a_failed_fit(
        ws: Workspace, model: AssemblyModel) -> None:
    """With every refinement taken as covering too little of its part, the parts of the intact
    assembly are not inspectable, never missing (the depth agrees with where they stand); a
    part left out is missing all the same."""
    mates = _mates(ws)
    failed = replace(QUIET, route=replace(QUIET.route, missing_coverage=1.01))
    intact = capture_variant(model, Variant(ASSEMBLY, "intact"), ws, QUIET)
    parts = inspect_capture(model, intact, mates, failed, fixture=np.eye(4))[0].parts
    assert {p.problem for p in parts.values()} == {"too little of it seen",
                                                  "too little of it visible"}
    face = mates[(mates["level"] == "face") & (mates["relation"] == "coincident")]
    gone = int(face.iloc[0]["index_a"])
    path = capture_variant(model, Variant(ASSEMBLY, "missing-test", (
        Defect(gone, "missing", 0.0),)), ws, QUIET)
    assert inspect_capture(model, path, mates, failed, fixture=np.eye(4))[0] \
        .parts[gone].problem == "missing"


def test_a_part_whose_points_the_sensor_dropped_is_not_missing_where_the_depth_agrees(
        ws: Workspace, model: AssemblyModel) -> None:
    """A part the design shows whose every point is gone from the scan (a ball between its
    neighbours shows a rim the sensor drops at the edges) while the depth images still agree
    with where it stands is "too little of it seen", not missing."""
    from cadio.inspect.routes import by_design

    path = capture_variant(model, Variant(ASSEMBLY, "intact"), ws, QUIET)
    scan = scan_of(list(read_capture(path)))
    few = replace(QUIET.route, missing_min_points=10**9)
    shown = [i for i, p in by_design(model, scan, few, np.eye(4))[1].items() if p.pose is not None]
    assert shown
    for i in shown:
        dropped = np.zeros(len(scan.points), dtype=bool)
        dropped[scan.segments[i + 1]] = True
        parts = by_design(model, scan.without(dropped), few, np.eye(4))[1]
        assert parts[i].problem == "too little of it seen", (i, parts[i].problem)


def test_the_search_route_never_reads_the_design_poses(ws: Workspace,
                                                       model: AssemblyModel) -> None:
    path = capture_variant(model, Variant(ASSEMBLY, "intact"), ws, QUIET)
    scan = scan_of(list(read_capture(path)))
    found = by_search(model, scan)
    rng = np.random.default_rng(0)
    nudged = []
    for pose in model.design:  # each design pose off by about a millimetre and a degree
        turn = np.eye(4)
        turn[:3, 3] = rng.normal(0, 1.0, 3)
        a = np.radians(1.0)
        turn[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
        nudged.append(turn @ pose)
    again = by_search(replace(model, design=tuple(nudged), _whole=[]), scan)
    truth = read_truth(ws, path.stem)
    # Which copy of a shape a segment is named follows the design's layout (the joint's two
    # washers are alike and stand symmetric about it: a tie the nudge may turn either way);
    # what the figures read does not: each segment's shape, its pose read as the part whose
    # points it registered (``scored_as``), and the uncertainty the relations read it within
    def registered(of: list[Found]) -> list[tuple[int, str, float]]:
        return sorted((f.segment, model.shapes[f.index], f.sigma_mm) for f in of)

    assert registered(found) == registered(again)
    read, read_again = scored_as(model, found, truth), scored_as(model, again, truth)
    assert read.keys() == read_again.keys() and len(read) == len(found)
    for segment, (index, pose) in read.items():
        assert read_again[segment][0] == index
        assert np.allclose(np.asarray(read_again[segment][1]), np.asarray(pose), rtol=0,
                           atol=1e-9)
    # noise-free, every segment found is explained exactly; its pose is within a millimetre
    # where the view holds it (a plate whose edges the two views hardly show slides in its
    # plane at no cost: 0.43 or 0.53 mm off, its fit exact either way, with each point alike
    # or weighed by its depth's sigma), read as the part whose points it registered
    assert len(found) >= 3 and all(f.fit.rmse_mm < 0.01 for f in found)
    errors = [pose_error(np.asarray(pose), np.array(truth["poses"][str(index)]),
                         model.symmetries[index]) for index, pose in read.values()]
    assert np.median([mm for mm, _ in errors]) < 1.0
    sigmas = [f.sigma_mm for f in found]  # noise-free: tight where the part is well seen
    assert all(0 < s < np.inf for s in sigmas) and np.median(sigmas) < 0.05


def test_a_capture_of_one_view_is_inspected_once_as_all_its_views_and_as_that_view(
        ws: Workspace, model: AssemblyModel, monkeypatch: pytest.MonkeyPatch) -> None:
    import cadio.inspect.stage as stage

    one = replace(QUIET, views=1, single_view=0)
    path = capture_variant(model, Variant(ASSEMBLY, "intact"), ws, one)
    calls: list[int] = []

    def counted(*args: object, **kwargs: object) -> object:
        calls.append(1)
        return by_design(*args, **kwargs)

    by_design = stage.by_design
    monkeypatch.setattr(stage, "by_design", counted)
    every, alone = inspect_capture(model, path, _mates(ws), one, fixture=np.eye(4))
    assert (every.views, alone.views) == ("all", "0") and len(calls) == 1
    assert alone.parts == every.parts and alone.mates == every.mates
    two = inspect_capture(model, capture_variant(model, Variant(ASSEMBLY, "intact"), ws,
                                                 replace(QUIET, single_view=0)),
                          _mates(ws), replace(QUIET, single_view=0), fixture=np.eye(4))
    assert [i.views for i in two] == ["all", "0"] and len(calls) == 3  # two views: each set


def test_an_assembly_s_inspection_rows(ws: Workspace) -> None:
    cfg = replace(QUIET, defects=DefectPlan(shifts_mm=(5.0,), turns_deg=(), missing=True,
                                            parts_per_variant=1), single_view=0)
    result = inspect_assembly(ASSEMBLY, ws, cfg, "test")
    assert not result.error and result.captures == 3
    tables = read_tables(Path(result.folder))
    defects = tables["defects"]
    assert set(defects["method"]) == {REGISTERED, DESIGN}
    assert not defects[defects["method"] == DESIGN]["caught"].any()
    assert defects[(defects["method"] == REGISTERED) & (defects["views"] == "all")][
        "caught"].all()
    intact = tables["parts"]
    intact = intact[(intact["variant"] == "intact") & (intact["method"] == REGISTERED)]
    assert not intact["flagged"].any()
    assert set(tables["poses"]["views"]) == {"all", "0"}


def test_registered_pairs_are_read_within_their_poses_uncertainty(ws: Workspace) -> None:
    """A part registered 0.4 mm off its coincident mate: within poses of 0.3 mm sigma each the
    mate holds (``registered``); at the CAD's 0.1 mm it does not (``registered_cad``)."""
    from cadio.camera.render import CaptureConfig, camera_pose
    from cadio.evidence.pairs import PosedScene, posed_pair_views
    from cadio.inspect.stage import part_ids
    from cadio.truth.relations import RELATIONS, contacts_of_mates
    from models.relate import assembly_pairs, load_relation_models, relate_views

    mates = _mates(ws)
    mate = mates[(mates["level"] == "face") & (mates["relation"] == "coincident")].iloc[0]
    ids = part_ids(ASSEMBLY, ws)
    truth = {pid: np.eye(4) for pid in ids}
    moved = {**truth, ids[int(mate["index_b"])]: np.eye(4)}
    moved[ids[int(mate["index_b"])]][:3, 3] = 0.4 * np.asarray(mate["axis"], dtype=float)
    known = PosedScene(ASSEMBLY, truth, list(assembly_pairs(mates)),
                       dict.fromkeys(ids, "assemblies"), contacts_of_mates(
                           mates.to_dict("records"), mates.attrs.get("near_boundary", [])))
    camera = camera_pose(CaptureConfig(distance_m=0.6), 0, np.zeros(3))
    views = posed_pair_views(known, {"registered": moved, "registered_cad": moved,
                                     "truth": truth}, [camera], ws,
                             sigmas={"registered": dict.fromkeys(ids, 0.3)})
    pair = {ids[int(mate["index_a"])], ids[int(mate["index_b"])]}
    view = next(v for v in views if {v.part_a, v.part_b} == pair)
    assert view.slack == {"registered": pytest.approx(0.3 * np.sqrt(2))}
    rows = pd.DataFrame(relate_views([view], load_relation_models(), ["geometric"]))
    coincident = rows[rows["relation"] == "coincident"].set_index("input")["predicted"]
    assert view.labels[RELATIONS.index("coincident")]
    assert coincident.to_dict() == {"truth": True, "registered": True,
                                    "registered_cad": False}


def test_the_search_s_near_ring_reaches_the_search_alone(ws: Workspace,
                                                         model: AssemblyModel) -> None:
    """The intact capture gains a near ring for the search route; the design route's checks
    read the ring around as they would without it, and the planted variants have none."""
    searched = replace(QUIET, search=True, search_near_m=0.3)
    intact = Variant(ASSEMBLY, "intact")
    path = capture_variant(model, intact, ws, searched)
    assert len(list(read_capture(path))) == 2 * QUIET.views
    with_ring = inspect_capture(model, path, _mates(ws), searched, search=True,
                                fixture=np.eye(4))[0]
    assert with_ring.found  # the search read the scan
    path = capture_variant(model, intact, ws, replace(searched, search_near_m=None))
    assert len(list(read_capture(path))) == QUIET.views
    without = inspect_capture(model, path, _mates(ws), searched, fixture=np.eye(4))[0]
    for i, part in without.parts.items():
        if part.pose is None:
            assert with_ring.parts[i].pose is None
        else:
            np.testing.assert_allclose(with_ring.parts[i].pose, part.pose, atol=1e-9)
    moved = Variant(ASSEMBLY, "shift-5mm", (Defect(0, "shift", 5.0, (1.0, 0.0, 0.0)),))
    assert len(list(read_capture(capture_variant(model, moved, ws, searched)))) == QUIET.views
