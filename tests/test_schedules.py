"""Schedules without a server: what a schedule's deployment holds, how `set` changes it, and
the command line's checks (the deployments themselves: tests/test_deployments.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import free_port

from flows.cli import _parser
from flows.cli_options import config_of, tolerances_of
from flows.config import ConfigError, ScheduledNight, validated
from flows.schedules import Schedule, merged, night_values, template, updated

ROOT = Path(__file__).resolve().parents[1]


def _config(*argv: str) -> ScheduledNight:
    args = _parser().parse_args(["schedule", *argv])
    args.tolerances = tolerances_of(args)
    config: ScheduledNight = config_of(args)
    return config


def test_a_schedule_keeps_only_the_options_given_with_absolute_paths(tmp_path: Path) -> None:
    config = _config("add", "heldout", "--library", "lib", "--views-per-scene", "3",
                     "--cron", "30 1 * * 1-5", "--timezone", "Europe/Berlin")
    assert (config.schedule.name, config.schedule.cron, config.schedule.timezone) == (
        "heldout", "30 1 * * 1-5", "Europe/Berlin")
    values = night_values(config, tmp_path)
    assert values == {"library": {"path": str(tmp_path / "lib")},
                      "capture": {"views_per_scene": 3},
                      "runtime": {"workspace": str(tmp_path / "heldout")}}  # named after it
    night = validated(ScheduledNight, {**values, "schedule": {"name": "heldout"}}).night()
    assert night.capture.pairs_per_relation == 4  # a field not given keeps its default


def test_tolerances_are_kept_only_when_given(tmp_path: Path) -> None:
    assert "tolerances" not in night_values(_config("add", "a"), tmp_path)
    values = night_values(_config("add", "a", "--tol", "contact_mm=0.2"), tmp_path)
    assert values["tolerances"]["contact_mm"] == 0.2


def test_set_changes_the_fields_given_and_keeps_the_rest(tmp_path: Path) -> None:
    stored = Schedule(name="heldout", cron="0 2 * * *", timezone="UTC", active=True,
                      config={"library": {"path": "/data/step", "categories": ["fasteners"]},
                              "runtime": {"workspace": "/data/ws/heldout"}})
    changed = updated(stored, _config("set", "heldout", "--cron", "15 3 * * *",
                                      "--views-per-scene", "2"), tmp_path)
    assert (changed.schedule.cron, changed.schedule.timezone) == ("15 3 * * *", "UTC")
    values = night_values(changed, tmp_path)
    assert values == {"library": {"path": "/data/step", "categories": ["fasteners"]},
                      "capture": {"views_per_scene": 2},
                      "runtime": {"workspace": "/data/ws/heldout"}}
    paused = updated(stored, _config("set", "heldout", "--no-active"), tmp_path)
    assert not paused.schedule.active and paused.schedule.cron == "0 2 * * *"
    moved = updated(stored, _config("set", "heldout", "--workspace", "elsewhere"), tmp_path)
    assert night_values(moved, tmp_path)["runtime"]["workspace"] == str(tmp_path / "elsewhere")


def test_merged_lays_groups_over_field_by_field() -> None:
    assert merged({"a": {"x": 1, "y": 2}, "b": 3}, {"a": {"y": 4}, "c": {"z": 5}}) == {
        "a": {"x": 1, "y": 4}, "b": 3, "c": {"z": 5}}


@pytest.mark.parametrize(("when", "field"), [
    ({"name": "a b"}, "schedule.name"),
    ({"name": "a", "cron": "61 * * * *"}, "schedule.cron"),
    ({"name": "a", "cron": "0 2 * *"}, "schedule.cron"),
    ({"name": "a", "timezone": "Mars/Olympus"}, "schedule.timezone"),
])
def test_a_bad_schedule_is_named_by_its_field(when: dict[str, str], field: str) -> None:
    with pytest.raises(ConfigError) as caught:
        validated(ScheduledNight, {"schedule": when})
    assert [named for named, _ in caught.value.problems] == [field]


def test_the_shipped_nightly_deployment_is_the_template() -> None:
    spec = template(ROOT)
    assert spec["entrypoint"] == "flows/nightly.py:nightly"
    assert spec["work_pool"]["name"] == "mateqa" and spec["concurrency_limit"] == 1


def _mateqa(*argv: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "flows.cli", *argv], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=120)


def test_without_a_server_the_command_says_how_to_start_one() -> None:
    env = {**os.environ, "PREFECT_API_URL": f"http://127.0.0.1:{free_port()}/api"}
    done = _mateqa("schedule", "list", env=env)
    assert done.returncode == 1 and "mateqa serve" in done.stderr, done.stderr


def test_a_bad_option_fails_before_the_server_is_asked() -> None:
    env = {**os.environ, "PREFECT_API_URL": f"http://127.0.0.1:{free_port()}/api"}
    done = _mateqa("schedule", "add", "x", "--cron", "every night", env=env)
    assert done.returncode == 2 and "--cron (schedule.cron)" in done.stderr, done.stderr
    assert json.dumps("x") not in done.stdout
