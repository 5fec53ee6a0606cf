"""The systemd units that keep `mateqa serve` (and a worker of its pool) up: they parse, name
commands that exist in this checkout, and pass `systemd-analyze verify` where it is installed
(that `mateqa serve` stops its worker and server on SIGTERM: tests/test_deployments.py)."""

from __future__ import annotations

import configparser
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
UNITS = sorted((ROOT / "systemd").glob("*.service"))
INSTALLED = "/opt/mateqa"  # where the units expect the checkout


def _unit(path: Path) -> configparser.ConfigParser:
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # type: ignore[assignment,method-assign]  # keys keep their case
    unit.read_string(path.read_text())
    return unit


def _here(path: Path, out: Path) -> Path:
    """The unit with this checkout in place of the installed one."""
    out.write_text(path.read_text().replace(INSTALLED, str(ROOT)))
    return out


def test_there_is_a_unit_for_serve_and_one_for_a_worker() -> None:
    commands = {p.name: shlex.split(_unit(p)["Service"]["ExecStart"]) for p in UNITS}
    serve = commands["mateqa.service"]
    assert serve[0] == f"{INSTALLED}/.venv/bin/mateqa" and serve[1] == "serve"
    assert serve[serve.index("--home") + 1] == "/var/lib/mateqa/prefect"
    worker = commands["mateqa-worker.service"]
    assert worker[1:] == ["worker", "start", "--pool", "mateqa", "--type", "process"]
    for path in UNITS:
        unit = _unit(path)
        assert unit["Install"]["WantedBy"] == "multi-user.target", path.name
        assert unit["Service"]["Restart"] == "on-failure", path.name
        assert unit["Service"]["WorkingDirectory"] == INSTALLED, path.name


def test_the_commands_exist_in_a_checkout() -> None:
    for path in UNITS:
        command = shlex.split(_unit(path)["Service"]["ExecStart"])[0]
        assert (ROOT / Path(command).relative_to(INSTALLED)).is_file(), command


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze here")
def test_systemd_verifies_the_units(tmp_path: Path) -> None:
    units = [_here(p, tmp_path / p.name) for p in UNITS]
    done = subprocess.run(["systemd-analyze", "verify", *map(str, units)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
