"""Predicted mates back into CAD: the XBF with XDE notes, the sidecar JSON and the CadQuery
script, on the nightly's real assemblies and on the CAD's own mates."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import jsonschema
import numpy as np
import pandas as pd
import pytest
from cad_oracle import oracle_record

from cadio.cad.step import read_step
from cadio.errors import StepReadError
from cadio.export.job import (
    ExportJob,
    export_assemblies,
    file_names,
    read_inputs,
    run_jobs,
)
from cadio.export.notes import read_notes, write_xbf
from cadio.export.predictions import (
    NO_PREDICTIONS,
    NOT_CAPTURED,
    OK,
    PARTIAL,
    PREDICTED,
    RELATIONS,
    assembly_mates,
)
from cadio.export.script import mass_properties, write_script
from cadio.export.sidecar import read_sidecar, schema, sidecar
from cadio.truth.mates import COLUMNS as MATES_COLUMNS
from reports.methods import product

# ----------------------------------------------------------------- pooling (plain pandas)

EYE = json.dumps(np.eye(4).ravel().tolist())


def _catalog(n: int) -> pd.DataFrame:
    return pd.DataFrame({"part_id": [f"p-{i}" for i in range(n)], "solid_index": range(n),
                         "name": [f"part {i}" for i in range(n)],
                         "path_in_assembly": [f"asm/part {i}" for i in range(n)],
                         "placement": [EYE] * n})


def _mates(rows: list[tuple[str, str, str, str]]) -> pd.DataFrame:
    """Mates rows (a, b, level, relation); joints get a kinematic name."""
    out = []
    for a, b, level, rel in rows:
        row = dict.fromkeys(MATES_COLUMNS)
        row.update(part_a=a, part_b=b, level=level, relation=rel,
                   kinematic=rel if level == "joint" else None)
        out.append(row)
    return pd.DataFrame(out, columns=list(MATES_COLUMNS))


def _views(a: str, b: str, answers: dict[str, list[tuple[bool, float]]],
           truth: set[str]) -> pd.DataFrame:
    rows = []
    for rel in RELATIONS:
        for view, (said, conf) in enumerate(answers.get(rel, [(False, 0.9)])):
            rows.append({"scene": "assembly-asm", "view": view, "part_a": a, "part_b": b,
                         "relation": rel, "truth": rel in truth, "predicted": said,
                         "confidence": conf})
    return pd.DataFrame(rows)


def test_views_are_pooled_by_their_calibrated_confidence() -> None:
    views = _views("p-0", "p-1", {
        "concentric": [(True, 0.9), (True, 0.8), (False, 0.6)],   # p = (0.9+0.8+0.4)/3 = 0.7
        "coincident": [(False, 0.9), (True, 0.7), (False, 0.9)],  # p = (0.1+0.7+0.1)/3 = 0.3
    }, truth={"concentric", "coincident"})
    mates = _mates([("p-0", "p-1", "joint", "revolute")])
    m = assembly_mates("asm", "assemblies", "asm.step", "", _catalog(2), mates, views)
    pair = m.pairs[0]
    conc, coin = pair.call("concentric"), pair.call("coincident")
    assert conc.predicted and conc.p_true == pytest.approx(0.7) and conc.views_true == 2
    assert not coin.predicted and coin.confidence == pytest.approx(0.7)
    assert conc.agrees and coin.agrees is False
    # concentric without coincident: a shaft that also slides; the CAD says revolute
    assert pair.joint.predicted == "cylindrical" and pair.joint.agrees is False
    assert pair.joint.confidence == pytest.approx(0.7 * 0.7)
    assert pair.joint.cad_names()["onshape"] == "Cylindrical"
    assert m.status == OK and pair.status == PREDICTED and pair.views == 3
    # a network with a joint head answers the joint of each view: the most views' answer wins
    said = {0: "revolute", 1: "revolute", 2: "planar"}
    headed = views.assign(joint=[said[int(v)] for v in views["view"]])
    joint = assembly_mates("asm", "assemblies", "asm.step", "", _catalog(2), mates,
                           headed).pairs[0].joint
    assert joint.predicted == "revolute" and joint.agrees
    assert joint.confidence == pytest.approx(2 / 3)


def test_a_pair_seen_the_other_way_round_takes_the_converse_relations() -> None:
    views = _views("p-1", "p-0", {"left": [(True, 0.9)]}, truth={"left"})
    m = assembly_mates("asm", "assemblies", "asm.step", "", _catalog(2), _mates([]), views)
    pair = m.pairs[0]
    assert (pair.a.index, pair.b.index) == (0, 1)
    assert pair.call("right").predicted and not pair.call("left").predicted
    assert pair.call("right").cad


def test_nothing_is_dropped_pairs_not_seen_and_assemblies_not_captured() -> None:
    mates = _mates([("p-0", "p-1", "part", "above"), ("p-1", "p-2", "joint", "planar")])
    seen = _views("p-0", "p-1", {"above": [(True, 0.8)]}, truth={"above"})
    partial = assembly_mates("asm", "assemblies", "asm.step", "", _catalog(3), mates, seen)
    assert partial.status == PARTIAL
    missing = next(p for p in partial.pairs if p.b.index == 2)
    assert missing.status == NOT_CAPTURED and missing.joint.predicted is None
    assert missing.joint.cad_kinematic == "planar"
    none = assembly_mates("asm", "assemblies", "asm.step", "", _catalog(3), mates,
                          seen.iloc[0:0])
    assert none.status == NO_PREDICTIONS and "not captured" in none.reason
    for record in (partial, none):  # both are valid sidecars, statuses included
        doc = sidecar(record)
        assert doc["status"] == record.status and len(doc["pairs"]) == 2


def test_the_schema_rejects_what_it_does_not_describe() -> None:
    doc = sidecar(assembly_mates("asm", "assemblies", "asm.step", "", _catalog(2), _mates([]),
                                 _views("p-0", "p-1", {}, set())))
    jsonschema.validate(doc, schema())
    bad = json.loads(json.dumps(doc))
    bad["pairs"][0]["joint"]["predicted"] = "welded"
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, schema())


# ----------------------------------------------------------------- the nightly's exports


def _exports(run: Path) -> pd.DataFrame:
    return pd.read_csv(run / "exports" / "index.csv")


def test_the_nightly_exports_every_assembly_with_three_files(local_night: Path) -> None:
    index = _exports(local_night)
    catalog = pd.read_parquet(local_night.parents[1] / "catalog.parquet")
    assemblies = {Path(s).stem for s in catalog[catalog["n_solids"] > 1]["source"]}
    assert set(index["assembly"]) == assemblies and assemblies
    assert set(index["status"]) <= {OK, PARTIAL}, index[["assembly", "status", "reason"]]
    for row in index.itertuples():
        folder = local_night / "exports" / row.assembly
        for name in file_names(row.assembly).values():
            assert (folder / name).is_file(), name


def test_the_sidecar_names_parts_as_the_step_file_does(local_night: Path) -> None:
    for row in _exports(local_night).itertuples():
        doc = read_sidecar(Path(row.sidecar))
        solids = read_step(Path(doc["source"]["path"]))
        assert [(p["index"], p["name"], p["path"]) for p in doc["parts"]] == [
            (s.info.index, s.info.name, s.info.path_in_assembly) for s in solids]
        assert doc["pairs"] and all(p["a"]["index"] < p["b"]["index"] for p in doc["pairs"])
        assert any(p["status"] == PREDICTED for p in doc["pairs"])
        assert doc["models"] and all(len(v) == 16 for v in doc["models"].values())


def test_the_xbf_reopens_with_every_note_on_its_parts(local_night: Path) -> None:
    for row in _exports(local_night).itertuples():
        doc = read_sidecar(Path(row.sidecar))
        notes = read_notes(Path(row.xbf))
        assert len(notes) == len(doc["parts"]) + len(doc["pairs"]) + 1 == row.notes
        solids = {s.info.index: s for s in read_step(Path(doc["source"]["path"]))}
        kinds = {"part": 0, "pair": 0, "assembly": 0}
        for note in notes:
            data = note.data  # the comment text is intact JSON
            kinds[data["kind"]] += 1
            assert note.user == "mateqa" and data["run_id"] == doc["run_id"]
            if data["kind"] == "part":
                s = solids[data["part"]["index"]]
                assert note.items == (("/".join(s.item), s.subshape),)
            if data["kind"] == "pair":
                ends = {("/".join(solids[data[k]["index"]].item),
                         solids[data[k]["index"]].subshape) for k in ("a", "b")}
                assert set(note.items) == ends
                mine = next(p for p in doc["pairs"] if p["a"]["index"] == data["a"]["index"]
                            and p["b"]["index"] == data["b"]["index"])
                assert data["joint"]["predicted"] == mine["joint"]["predicted"]
        assert kinds == {"part": len(doc["parts"]), "pair": len(doc["pairs"]), "assembly": 1}


def test_the_export_carries_each_cad_mate_as_built(local_night: Path) -> None:
    """The night inspected its assembly: each face mate's check (status, residuals against
    their thresholds) is in the sidecar, and in the notes of its pair."""
    as_built = pd.read_csv(local_night / "as_built.csv")
    assert not as_built.empty
    for row in _exports(local_night).itertuples():
        doc = read_sidecar(Path(row.sidecar))
        mine = as_built[as_built["assembly"] == row.assembly]
        checks = doc["as_built"]["mates"]
        assert len(checks) == len(mine) > 0
        assert [c["status"] for c in checks] == list(mine["status"])
        held = [c for c in checks if c["status"] == "holds"]
        for c in held:
            assert c["residuals"] and all(r["value"] <= r["threshold"]
                                          for r in c["residuals"].values())
        assert doc["as_built"]["verdict"]
        notes = [n.data for n in read_notes(Path(row.xbf))]
        assembly = next(n for n in notes if n["kind"] == "assembly")
        assert assembly["as_built"] == doc["as_built"]["verdict"]
        in_pairs = sum(len(n["as_built"]) for n in notes if n["kind"] == "pair")
        paired = {(p["a"]["index"], p["b"]["index"]) for p in doc["pairs"]}
        assert in_pairs == sum((min(c["index_a"], c["index_b"]),
                                max(c["index_a"], c["index_b"])) in paired for c in checks)


def _solve(script: Path, tmp: Path, *args: str) -> dict:
    out = tmp / f"{script.stem}.json"
    proc = subprocess.run([sys.executable, str(script), "--json", str(out), *args],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode in (0, 1), proc.stderr[-2000:]
    return json.loads(out.read_text())


def test_the_cadquery_script_solves_back_to_the_step_placements(local_night: Path,
                                                               tmp_path: Path) -> None:
    for row in _exports(local_night).itertuples():
        result = _solve(Path(row.script), tmp_path, "--perturb", "0.5")
        step = {s.info.index: s.info.placement for s in
                read_step(Path(read_sidecar(Path(row.sidecar))["source"]["path"]))}
        assert result["reproduced"] and result["constraints_hold"], result
        for part in result["parts"]:  # against the file read again, not the script's copy
            got = np.asarray(part["placement"]).reshape(4, 4)
            assert np.abs(got - step[part["index"]]).max() < 1e-3


@pytest.fixture(params=["real arbor press", "sample swivel caster"])
def cad_assembly(request: pytest.FixtureRequest, shared_step_dir: Path,
                 tmp_path: Path) -> Path:
    """A real assembly from ../shared (coincident mates) or a sample one (shafts in bores)."""
    if request.param.startswith("real"):
        return shared_step_dir / "assemblies" / "abc_00509609_arbor-press.step"
    from cadio.cad.step import write_step
    from cadio.samples.library import sample_specs

    spec = next(s for s in sample_specs() if s.name == "swivel-caster-d75")
    path = tmp_path / "swivel-caster-d75.step"
    write_step(spec.build(), path)
    return path


def test_every_cad_mate_as_a_constraint_pulls_perturbed_parts_back(cad_assembly: Path,
                                                                   tmp_path: Path) -> None:
    """With the CAD's own answers as predictions, every concentric and coincident face mate
    is a constraint: parts started 1 mm off come back to the file's placements; a mate moved
    by 1 mm moves its part (the check can fail)."""
    oracle, solids, mates = oracle_record(cad_assembly)
    assert oracle.status == OK
    constrained = sum(len(p.constraints()) for p in oracle.pairs)
    assert constrained == int(((mates["level"] == "face")
                               & mates["relation"].isin(["concentric", "coincident"])).sum())
    assert constrained > 0
    script = write_script(tmp_path / "oracle.py", oracle, cad_assembly,
                          mass_properties(solids), 0.1, 0.5)
    result = _solve(script, tmp_path, "--perturb", "1.0")
    moved = [p for p in result["parts"] if p["start_offset_mm"] > 0.99]
    assert moved and result["reproduced"] and result["constraints_hold"], result
    text = script.read_text()
    embedded = re.search(r'r"""\n(.*)\n"""', text, re.DOTALL).group(1)
    data = json.loads(embedded)
    mate = next(c for c in data["constraints"] if c["kind"] == "PointInPlane"
                and c["mate"] == "coincident")
    point, normal = (np.asarray(v) for v in mate["b_marker"]["plane"])
    mate["b_marker"]["plane"][0] = (point + 1.0 * normal).tolist()
    tampered = tmp_path / "tampered.py"
    tampered.write_text(text.replace(embedded, json.dumps(data)))
    assert not _solve(tampered, tmp_path)["reproduced"]


def test_a_file_that_changed_since_the_run_is_exported_as_failed(local_night: Path,
                                                                tmp_path: Path) -> None:
    jobs = run_jobs(local_night.parents[1], local_night, {}, tmp_path / "out",
                    answers=product())
    good = jobs[0]
    broken = tmp_path / "broken.step"
    broken.write_bytes(Path(good.step).read_bytes()[:2000])  # truncated since the run
    bad = ExportJob(**{**good.__dict__, "step": str(broken), "assembly": "broken",
                       "out": str(tmp_path / "out" / "broken")})
    bad_catalog = pd.read_parquet(good.catalog)
    bad_catalog.loc[bad_catalog["source"] == good.step, "source"] = str(broken)
    bad_catalog.to_parquet(tmp_path / "catalog.parquet")
    bad = ExportJob(**{**bad.__dict__, "catalog": str(tmp_path / "catalog.parquet")})
    summaries = {s.assembly: s for s in export_assemblies([good, bad])}
    assert summaries[good.assembly].status in (OK, PARTIAL)
    failed = summaries["broken"]
    assert failed.status == "failed" and "truncated" in failed.reason
    doc = read_sidecar(Path(failed.sidecar))
    assert doc["status"] == "failed" and doc["reason"] == failed.reason


def test_mateqa_export_writes_what_the_nightly_wrote(local_night: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    from flows.cli import main

    workspace = local_night.parents[1]
    code = main(["export", "--workspace", str(workspace), "--run", local_night.name, "--out",
                 str(tmp_path)])
    out = capsys.readouterr()
    assert code == 0, out.err[-2000:]
    for row in _exports(local_night).itertuples():
        assert row.assembly in out.out
        mine = json.loads((tmp_path / row.assembly / Path(row.sidecar).name).read_text())
        assert mine == json.loads(Path(row.sidecar).read_text())


def test_notes_need_the_parts_of_the_run(local_night: Path, tmp_path: Path,
                                         shared_step_dir: Path) -> None:
    """An XBF is never written for a file whose solids are not the run's parts."""
    job = run_jobs(local_night.parents[1], local_night, {}, tmp_path, answers=product())[0]
    record = read_inputs(job)
    other = shared_step_dir / "assemblies" / "occt_as1_motor.step"
    with pytest.raises(StepReadError, match="is not the part"):
        write_xbf(other, record, tmp_path / "x.xbf", "2026-01-01T00:00:00+00:00")
    assert not (tmp_path / "x.xbf").exists()
