"""The ``mateqa`` command line: help everywhere, exit codes that mean what they say."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from cadio.catalog import read_catalog
from flows.cli import _parser, main

SUBCOMMANDS = sorted(_parser()._subparsers._group_actions[0].choices)  # type: ignore[union-attr]


@pytest.mark.parametrize("command", SUBCOMMANDS)
def test_every_subcommand_has_help(command: str) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "flows.cli", command, "--help"],
        capture_output=True, text=True, check=False,
    )
    assert out.returncode == 0, out.stderr
    assert f"usage: mateqa {command}" in out.stdout


def test_required_subcommands_exist() -> None:
    assert {"ingest", "nightly"} <= set(SUBCOMMANDS)


def test_ingest_exits_zero_with_bad_inputs_and_reports_them(
    tmp_path: Path, box_step: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lib = tmp_path / "lib" / "fasteners"
    lib.mkdir(parents=True)
    shutil.copy(box_step, lib / "good.step")
    (lib / "bad.step").write_text("not a step file")
    code = main(["ingest", str(lib.parent), "--workspace", str(tmp_path / "ws"),
                 "--voxel-sizes", "16", "--workers", "1"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "2 files found: 1 ok, 1 failed" in printed
    assert "bad.step" in printed and "not a STEP file" in printed
    catalog = read_catalog(tmp_path / "ws" / "catalog.parquet")
    assert sorted(catalog["status"]) == ["failed", "ok"]


def test_ingest_of_a_missing_folder_fails_the_run(tmp_path: Path) -> None:
    code = main(["ingest", str(tmp_path / "nope"), "--workspace", str(tmp_path / "ws")])
    assert code == 2


def test_train_writes_into_its_workspace_and_ship_is_the_explicit_step(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from flows.cli_options import config_of
    from models.checkpoint import load_checkpoint, ship_checkpoints
    from models.evaluate import SHIPPED
    from models.training.run import out_dir

    ws = tmp_path / "train-ws"
    for stage in ("completion", "relations"):
        args = _parser().parse_args(["train", stage, "--workspace", str(ws)])
        assert out_dir(config_of(args), stage) == (ws / "checkpoints" / stage).resolve()
    # Nothing trained there yet: shipping refuses, naming the folder, and ships nothing.
    assert main(["ship", "completion", "--workspace", str(ws)]) == 2
    assert f"{ws.resolve() / 'checkpoints' / 'completion'}: no checkpoint" in \
        capsys.readouterr().err
    trained, shipped = ws / "checkpoints" / "completion", tmp_path / "shipped"
    trained.mkdir(parents=True)
    shutil.copy(SHIPPED / "completion-ae-observed.pt", trained)
    (trained / "MODEL_CARD.md").write_text("# trained here\n")
    shipped.mkdir()
    (shipped / "completion-r2n2-observed.pt").write_bytes(b"kept")
    (shipped / "MODEL_CARD.md").write_text("# the old card\n")
    files = ship_checkpoints(trained, shipped)
    assert sorted(f.name for f in files) == ["MODEL_CARD.md", "completion-ae-observed.pt"]
    assert (shipped / "MODEL_CARD.md").read_text() == "# trained here\n"
    assert load_checkpoint(shipped / "completion-ae-observed.pt")["method"] == "ae"
    assert (shipped / "completion-r2n2-observed.pt").read_bytes() == b"kept"
    assert sorted(p.name for p in shipped.iterdir()) == [
        "MODEL_CARD.md", "completion-ae-observed.pt", "completion-r2n2-observed.pt"]
