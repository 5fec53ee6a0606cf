"""Every bad input gets a clear answer: no hang, no lost batch, no traceback, no silent pass.

The first table holds the options and settings files: each must stop the command before any
work (exit 2, no workspace made) with one line naming the option or file and the reason. The
tests after it hold the inputs a night must survive: named pipes, devices, names that are not
UTF-8 or hold a newline, a CSV that lists a file twice, a file that crashes OpenCascade under
``mates`` and ``capture``, recordings that are folders or of another library, damaged
checkpoints, a SIGTERM mid-night, and the modes of the files written.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from conftest import ONE_THREAD

from cadio.cad.ingest import IngestConfig, discover, ingest
from cadio.sandbox import Limits
from flows.cli import main

ROOT = Path(__file__).resolve().parents[1]
FAST = IngestConfig(voxel_sizes=(16,), limits=Limits(seconds=120, workers=1))
# Where no server answers: a command that got past its checks would fail at once, not start one.
NO_SERVER = "http://127.0.0.1:9/api"


@pytest.fixture()
def inputs(tmp_path: Path, box_step: Path) -> Path:
    """A folder of inputs, good and bad, for the table below."""
    lib = tmp_path / "lib"
    (lib / "fasteners").mkdir(parents=True)
    shutil.copy(box_step, lib / "fasteners" / "box.step")
    (tmp_path / "empty-lib").mkdir()
    (tmp_path / "empty-dir").mkdir()
    (tmp_path / "a-file").write_text("x")
    (tmp_path / "empty.csv").write_bytes(b"")
    (tmp_path / "no-category.csv").write_text(f"path,category\n{box_step},\n")
    (tmp_path / "null.json").write_text('{"contact_mm": null}')
    (tmp_path / "syntax.json").write_text('{"contact_mm": 0.2,}')
    for name, text in {"cat5": "[completion_iou]\nfloor = 0.1\ncategories = 5\n",
                       "catnum": "[completion_iou.categories]\nfasteners = 0.5\n",
                       "flor": "[completion_iou]\nflor = 1.01\n",
                       "nan": "[completion_iou]\nfloor = nan\n"}.items():
        (tmp_path / f"{name}.toml").write_text(text)
    (tmp_path / "random-relations").mkdir()
    (tmp_path / "random-relations" / "ltn-truth.pt").write_bytes(  # IndexError in torch.load
        np.random.default_rng(17).bytes(4096))
    (tmp_path / "random-completion").mkdir()
    (tmp_path / "random-completion" / "completion-gan_lstm-observed.pt").write_bytes(
        np.random.default_rng(0).bytes(4096))
    (tmp_path / "ws-latest" / "runs" / "latest").mkdir(parents=True)  # a folder, not the link
    runs = tmp_path / "ws-runs" / "runs"
    (runs / "20260101T000000000000Z").mkdir(parents=True)  # killed: no summary.json
    (runs / "20260102T000000000000Z").mkdir()
    (runs / "20260102T000000000000Z" / "summary.json").write_text("{}")
    return tmp_path


NIGHT = ["nightly", "--library", "{d}/lib", "--workspace", "{d}/ws"]
INGEST = ["ingest", "{d}/lib", "--workspace", "{d}/ws"]
# (command line, what the one line must name): exit 2 before any work.
OPTION_CASES: dict[str, tuple[list[str], list[str]]] = {
    "0-byte library CSV": (["nightly", "--library", "{d}/empty.csv", "--workspace", "{d}/ws"],
                           ["empty.csv", "empty"]),
    "CSV row without category": (["ingest", "{d}/no-category.csv", "--workspace", "{d}/ws"],
                                 ["no-category.csv", "line 2", "no category"]),
    "--tolerances with null": ([*INGEST, "--tolerances", "{d}/null.json"],
                               ["null.json", "contact_mm", "must be a number"]),
    "--tolerances syntax error": ([*INGEST, "--tolerances", "{d}/syntax.json"],
                                  ["syntax.json", "not JSON"]),
    "--workers -1": ([*INGEST, "--workers", "-1"], ["--workers", "0 to 256", "-1"]),
    "thresholds categories = 5": ([*NIGHT, "--thresholds", "{d}/cat5.toml"],
                                  ["cat5.toml", "categories must be a table"]),
    "thresholds category of numbers": ([*NIGHT, "--thresholds", "{d}/catnum.toml"],
                                       ["catnum.toml", "fasteners", "must be a table"]),
    "thresholds key typo": ([*NIGHT, "--thresholds", "{d}/flor.toml"], ["flor.toml", "'flor'"]),
    "thresholds floor nan": ([*NIGHT, "--thresholds", "{d}/nan.toml"], ["nan.toml", "finite"]),
    "--workspace a file": ([*INGEST[:2], "--workspace", "{d}/a-file"],
                           ["--workspace", "is a file"]),
    "--out a file": (["export", "--workspace", "{d}/ws-runs", "--run", "20260102T000000000000Z",
                      "--out", "{d}/a-file"], ["--out", "a-file", "is a file"]),
    "export of a killed run": (["export", "--workspace", "{d}/ws-runs", "--run",
                                "20260101T000000000000Z"], ["--run", "did not complete"]),
    "mates on a missing file": (["mates", "{d}/nope.step", "--workspace", "{d}/ws"],
                                ["nope.step", "does not exist"]),
    "mates on a folder": (["mates", "{d}/empty-dir", "--workspace", "{d}/ws"],
                          ["empty-dir", "is not a file"]),
    "--captures missing": ([*NIGHT, "--captures", "{d}/nope"],
                           ["--captures", "nope", "not a folder"]),
    "--captures without recordings": ([*NIGHT, "--captures", "{d}/empty-dir"],
                                      ["--captures", "no recording"]),
    "--categories typo": ([*NIGHT, "--categories", "fastners"], ["'fastners'", "fasteners"]),
    "empty library": (["nightly", "--library", "{d}/empty-lib", "--workspace", "{d}/ws"],
                      ["empty-lib", "would check nothing"]),
    "--history -1": ([*NIGHT, "--history", "-1"], ["--history", "0 to 365"]),
    "--completion-models empty": ([*NIGHT, "--completion-models", "{d}/empty-dir"],
                                  ["--completion-models", "no checkpoint"]),
    "--relation-models empty": ([*NIGHT, "--relation-models", "{d}/empty-dir"],
                                ["--relation-models", "no checkpoint"]),
    "relation checkpoint of random bytes": ([*NIGHT, "--relation-models", "{d}/random-relations"],
                                            ["ltn-truth.pt", "not a checkpoint"]),
    "completion checkpoint of random bytes": (
        [*NIGHT, "--completion-models", "{d}/random-completion"],
        ["completion-gan_lstm-observed.pt", "not a checkpoint"]),
    "--views 0": (["capture", "{d}/lib/fasteners/box.step", "--workspace", "{d}/ws", "--views",
                   "0"], ["--views", "1 to 125"]),
    "--views-per-scene 0": ([*NIGHT, "--views-per-scene", "0"], ["--views-per-scene", "1 to 125"]),
    "--pairs-per-relation 0": ([*NIGHT, "--pairs-per-relation", "0"],
                               ["--pairs-per-relation", "1 to 1000"]),
    "--voxel-sizes 0": ([*INGEST, "--voxel-sizes", "0"], ["--voxel-sizes", "8 to 256"]),
    "--timeout 0": ([*INGEST, "--timeout", "0"], ["--timeout", "> 0"]),
    "--memory-mb 1": ([*INGEST, "--memory-mb", "1"], ["--memory-mb", "2048"]),
    "--max-file-mb -1": ([*INGEST, "--max-file-mb", "-1"], ["--max-file-mb", "> 0"]),
    "--workspace /": (["nightly", "--library", "{d}/lib", "--workspace", "/"],
                      ["--workspace (runtime.workspace)", "/ is the filesystem root"]),
    "--workspace a folder of other files": (["ingest", "{d}/lib", "--workspace", "{d}"],
                                            ["--workspace", "not empty and not a mateqa "
                                             "workspace", "a-file"]),
    "a folder at runs/latest": (["nightly", "--library", "{d}/lib", "--workspace",
                                 "{d}/ws-latest"], ["ws-latest/runs/latest is not the link"]),
    "PREFECT_API_URL where no server answers": (NIGHT, ["no Prefect API answers at "
                                                        f"{NO_SERVER} (PREFECT_API_URL)"]),
}


@pytest.mark.parametrize("case", OPTION_CASES)
def test_a_bad_option_or_settings_file_stops_before_any_work(
        case: str, inputs: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    argv, named = OPTION_CASES[case]
    monkeypatch.setenv("PREFECT_API_URL", NO_SERVER)
    code = main([a.format(d=inputs) for a in argv])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("mateqa")]
    assert code == 2, err[-2000:]
    assert len(lines) == 1 and "Traceback" not in err, err[-2000:]
    for word in named:
        assert word in lines[0], lines[0]
    assert "weights_only" not in err  # torch's advice to run a file's code never reaches a user
    assert not (inputs / "ws").exists()  # before any work


def test_a_bad_environment_variable_is_named(monkeypatch: pytest.MonkeyPatch,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("MATEQA_WORKERS", "-1")
    assert main(["samples", "--help"]) == 2
    assert "MATEQA_WORKERS='-1'" in capsys.readouterr().err


# ---------------------------------------------------------------- inputs a night survives


def _row(catalog: pd.DataFrame, name: str) -> pd.Series:
    rows = catalog[catalog["source"].str.endswith(name)]
    assert len(rows) == 1, f"{name}: {len(rows)} rows"
    return rows.iloc[0]


def test_pipes_and_devices_are_never_read_and_odd_names_keep_the_batch(
        tmp_path: Path, box_step: Path) -> None:
    lib = tmp_path / "lib" / "fasteners"
    lib.mkdir(parents=True)
    shutil.copy(box_step, lib / "good.step")
    os.mkfifo(lib / "pipe.step")  # no writer: the first read would block for ever
    (lib / "zero.step").symlink_to("/dev/zero")  # endless
    odd = os.fsencode(lib) + b"/bad\xff\xfename.step"  # not UTF-8
    Path(os.fsdecode(odd)).write_bytes(box_step.read_bytes().replace(b"box", b"bad"))
    (lib / "two\nlines.step").write_text("not a STEP file\n")
    catalog = ingest(lib.parent, tmp_path / "ws", FAST)  # returns: nothing blocked
    assert _row(catalog, "good.step")["status"] == "ok"
    assert "named pipe" in _row(catalog, "pipe.step")["error"]
    assert "character device" in _row(catalog, "zero.step")["error"]
    bad = _row(catalog, "bad\\xff\\xfename.step")
    assert bad["status"] == "skipped" and "not valid UTF-8" in bad["error"]
    assert (tmp_path / "ws" / "catalog.parquet").is_file()  # written: the batch is kept

    from reports.render import build_ingest_report

    markdown = build_ingest_report(catalog).markdown()
    row = next(line for line in markdown.splitlines() if "two" in line)
    assert "two\\nlines.step" in row and row.endswith("|")  # one row, one line


def test_a_csv_saved_by_a_spreadsheet_listing_a_file_twice_reads_each_file_once(
        tmp_path: Path, box_step: Path) -> None:
    listing = tmp_path / "library.csv"
    rows = f"path,category\r\n{box_step},fasteners\r\n{box_step},plates\r\n"
    listing.write_bytes("\ufeff".encode() + rows.encode())  # with a byte-order mark
    found = discover(listing)
    assert [(f.path, f.category) for f in found] == [(box_step, "fasteners")]
    catalog = ingest(listing, tmp_path / "ws", FAST)
    assert catalog["part_id"].is_unique and list(catalog["status"]) == ["ok"]


def _self_related(path: Path) -> None:
    """A two-part assembly whose first part's representation is related to itself: it crashes
    OpenCascade's STEP reader (SIGSEGV)."""
    import build123d as bd

    from cadio.cad.step import write_step

    a, b = bd.Box(10, 10, 10), bd.Pos(10, 0, 0) * bd.Box(10, 10, 10)
    a.label, b.label = "a", "b"
    write_step(bd.Compound(children=[a, b], label="loop"), path)
    text = path.read_text()
    first = re.search(r"REPRESENTATION_RELATIONSHIP\('','',#(\d+),#(\d+)\)", text)
    assert first is not None
    self_related = f"REPRESENTATION_RELATIONSHIP('','',#{first[2]},#{first[2]})"
    path.write_text(text.replace(first[0], self_related, 1))


@pytest.mark.parametrize("command", [["mates"], ["capture", "--views", "2"]])
def test_a_file_that_crashes_opencascade_is_a_named_error(
        command: list[str], tmp_path: Path) -> None:
    step = tmp_path / "loop.step"
    _self_related(step)
    done = subprocess.run([sys.executable, "-m", "flows.cli", command[0], str(step),
                           "--workspace", str(tmp_path / "ws"), *command[1:]], cwd=ROOT,
                          capture_output=True, text=True)
    assert done.returncode == 2, done.stderr[-2000:]  # not 139
    assert f"{step}: the reader crashed inside the CAD kernel (SIGSEGV)" in done.stderr


def test_mates_of_a_single_part_says_so(box_step: Path, tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["mates", str(box_step), "--workspace", str(tmp_path / "ws")]) == 0
    out = capsys.readouterr().out
    assert "one part has no pair" in out and "Series" not in out


def test_recordings_that_are_folders_or_of_another_library_are_named_and_the_rest_goes_on(
        tmp_path: Path, box_step: Path) -> None:
    from cadio.capture.scan import ScanConfig, capture_step, read_captures
    from cadio.workspace import Workspace

    cfg = ScanConfig(views_per_scene=2)
    recorded = capture_step(str(box_step), tmp_path / "elsewhere", cfg)
    folder = tmp_path / "recordings"
    (folder / "a-folder.mcap").mkdir(parents=True)
    shutil.copy(recorded.path, folder / "foreign.mcap")
    ws = Workspace(tmp_path / "ws")
    ws.root.mkdir()
    out = {Path(c.path).name: c.error for c in read_captures(folder, ws, cfg)}
    assert "not a regular file" in out["a-folder.mcap"]
    assert "not in the library's catalog" in out["foreign.mcap"]


def test_damaged_checkpoints_are_named_without_torch_advice(tmp_path: Path) -> None:
    from models.checkpoint import load_checkpoint
    from models.errors import CheckpointError
    from models.relate import load_relation_models

    folder = tmp_path / "relations"
    folder.mkdir()
    for seed, name in [(17, "ltn-truth.pt"), (54, "ltn-partial.pt"), (62, "mlp-truth.pt")]:
        (folder / name).write_bytes(np.random.default_rng(seed).bytes(4096))
    errors = load_relation_models(folder).errors
    assert sorted(e.split(":")[0] for e in errors) == sorted(
        ["ltn-partial.pt", "ltn-truth.pt", "mlp-truth.pt"])
    (folder / "pickle.pt").write_bytes(b"\x80\x04\x95\x05\x00\x00\x00\x00\x00\x00\x00}\x94.")
    for path in folder.glob("*.pt"):
        with pytest.raises(CheckpointError, match=re.escape(str(path))) as caught:
            load_checkpoint(path)
        assert "weights_only" not in str(caught.value)


def test_files_are_written_as_the_umask_says(tmp_path: Path, box_step: Path) -> None:
    lib = tmp_path / "lib" / "fasteners"
    lib.mkdir(parents=True)
    shutil.copy(box_step, lib / "box.step")
    before = os.umask(0o027)
    try:
        ingest(lib.parent, tmp_path / "ws", FAST)
    finally:
        os.umask(before)
    written = [p for p in (tmp_path / "ws").rglob("*") if p.is_file()]
    assert len(written) >= 4  # catalog, mesh, features, voxels
    assert {oct(p.stat().st_mode & 0o777) for p in written} == {oct(0o640)}


# ---------------------------------------------------------------- SIGTERM mid-night


def _flow_runs(env: dict[str, str], workspace: Path) -> list[Any]:
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL, temporary_settings

    async def read() -> list[Any]:  # every run of the server, a page at a time
        runs: list[Any] = []
        async with get_client() as client:
            while True:
                page = await client.read_flow_runs(offset=len(runs), limit=100)
                runs += page
                if len(page) < 100:
                    return runs

    with temporary_settings({PREFECT_API_URL: env["PREFECT_API_URL"]}):
        runs = asyncio.run(read())
    return [r for r in runs if json.dumps(r.parameters).count(str(workspace))]


def _session(pid: int) -> list[int]:
    """Processes left in the session ``pid`` led."""
    left = []
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and os.getsid(int(entry.name)) == pid:
                left.append(int(entry.name))
        except OSError:  # gone while listed
            continue
    return left


def _wait(condition: Callable[[], bool], what: str, limit_s: float = 600) -> None:
    """Poll until ``condition`` (a guard against a hang, not a speed check)."""
    deadline = time.monotonic() + limit_s
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.2)


@pytest.mark.server
def test_the_first_sigterm_stops_a_night_at_once_and_marks_its_runs(
        shared_step_dir: Path, prefect_api: dict[str, str], tmp_path: Path) -> None:
    lib = tmp_path / "lib" / "assemblies"
    lib.mkdir(parents=True)
    pump = shared_step_dir / "assemblies" / "occt_pm4_rotor-pump-assembly.stp"
    shutil.copy(pump, lib)  # 32 solids: its CAD worker is busy for many seconds
    ws = tmp_path / "ws"
    log = tmp_path / "night.log"
    with log.open("wb") as out:
        night = subprocess.Popen(
            [sys.executable, "-m", "flows.cli", "nightly", "--library", str(lib.parent),
             "--workspace", str(ws), "--views-per-scene", "1", "--pairs-per-relation", "1",
             "--workers", "1", "--no-fail-on-threshold"], cwd=ROOT, stdout=out,
            stderr=subprocess.STDOUT, start_new_session=True,
            env={**prefect_api, **ONE_THREAD})
    meshes = ws / "meshes"
    _wait(lambda: night.poll() is not None or any(meshes.glob("*.ply")), "no mesh written")
    assert night.poll() is None, log.read_text()[-3000:]
    night.send_signal(signal.SIGTERM)  # the one signal: no second one, no SIGKILL
    _wait(lambda: night.poll() is not None, "the night ignored SIGTERM")
    # the pump's worker was stopped mid-file, not waited for
    assert len(list(meshes.glob("*.ply"))) < 32, log.read_text()[-3000:]
    assert night.returncode in (-signal.SIGTERM, 128 + signal.SIGTERM)
    _wait(lambda: not _session(night.pid), "a CAD worker outlived the night")
    runs = _flow_runs(prefect_api, ws)
    assert len(runs) == 2  # nightly and its stages
    for run in runs:
        assert run.state.name == "Crashed" and "SIGTERM" in run.state.message
    assert not list(ws.glob("runs/*/summary.json"))
