"""End to end, as a QA engineer types it: `mateqa serve` (a real local Prefect server, a
process work pool and worker, the deployments of prefect.yaml), then
`prefect deployment run 'nightly/nightly' --param 'config={...}' --watch`, on real STEP
files."""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from uuid import UUID

import pandas as pd
import pytest
from conftest import ONE_THREAD, TEST_INSPECTION, free_port

from cadio.tolerances import DEFAULT_TOLERANCES

pytestmark = pytest.mark.server

ROOT = Path(__file__).resolve().parents[1]
RUN_FILES = ["report.html", "categories.csv", "junit.xml", "parts.parquet", "pairs.parquet",
             "exports/index.csv",
             "completion_parts.parquet", "relations_summary.csv", "assembly_mates.csv",
             "tolerances.json", "summary.json"]


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    """`mateqa serve` running; yields the environment of a client of its server."""
    home, port = tmp_path_factory.mktemp("serve-home"), free_port()
    log = home / "serve.out"
    with log.open("wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "flows.cli", "serve", "--port",
                                 str(port), "--home", str(home)], cwd=ROOT, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True,
                                env={**os.environ, **ONE_THREAD,
                                     "PREFECT_WORKER_QUERY_SECONDS": "2",
                                     "PREFECT_SERVER_SERVICES_SCHEDULER_LOOP_SECONDS": "2"})
    deadline = time.monotonic() + 300
    while "Ctrl-C stops" not in log.read_text() and time.monotonic() < deadline:
        assert proc.poll() is None, log.read_text()
        time.sleep(0.5)
    env = {**os.environ, "PREFECT_API_URL": f"http://127.0.0.1:{port}/api"}
    yield env
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(60) == 0, log.read_text()  # stops cleanly, worker and server with it
    assert "mateqa serve: stopped" in log.read_text()


def _client_call(env: dict[str, str], fn: Any) -> Any:
    """Run ``fn(client)`` against the served API (settings read from ``env``)."""
    from prefect.settings import PREFECT_API_URL, temporary_settings

    async def call() -> Any:
        from prefect.client.orchestration import get_client

        async with get_client() as client:
            return await fn(client)

    with temporary_settings({PREFECT_API_URL: env["PREFECT_API_URL"]}):
        return asyncio.run(call())


def _prefect(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(Path(sys.executable).with_name("prefect")), *args], env=env,
                          cwd=ROOT, capture_output=True, text=True, timeout=900)


def _deployment_run(env: dict[str, str],
                    config: dict[str, Any]) -> subprocess.CompletedProcess[str]:
    """``prefect deployment run 'nightly/nightly' --param config=... --watch``."""
    return _prefect(env, "deployment", "run", "nightly/nightly", "--param",
                    f"config={json.dumps(config)}", "--watch")


def _final_state(env: dict[str, str], watched: subprocess.CompletedProcess[str]) -> Any:
    """The final state of the flow run a ``_deployment_run`` watched, read from the server:
    it carries the reason, which the watch prints only if its logs arrive in time."""
    said = watched.stdout + watched.stderr
    run_id = re.search(r"UUID: ([0-9a-f-]{36})", said)
    assert run_id is not None, said[-3000:]
    state = _client_call(env, lambda client: client.read_flow_run(UUID(run_id[1]))).state
    assert state is not None and state.name == "Failed", said[-3000:]
    return state


def _run_nightly(env: dict[str, str], library: Path, workspace: Path) -> str:
    done = _deployment_run(env, {
        "library": {"path": str(library)}, "runtime": {"workspace": str(workspace)},
        "capture": {"views_per_scene": 1, "pairs_per_relation": 1},
        "inspection": TEST_INSPECTION, "thresholds": {"fail_on_threshold": False}})
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-4000:]
    return done.stdout


def test_the_deployments_are_applied_with_a_schedule_and_a_limit(
        served: dict[str, str]) -> None:
    async def read(client: Any) -> Any:
        deployments = await client.read_deployments()
        nightly = next(d for d in deployments if d.name == "nightly")
        runs = await client.read_flow_runs()
        return deployments, nightly, [r for r in runs if r.deployment_id == nightly.id]

    deadline = time.monotonic() + 120
    while True:  # the scheduler service inserts the cron's next runs shortly after deploying
        deployments, nightly, scheduled = _client_call(served, read)
        if scheduled or time.monotonic() > deadline:
            break
        time.sleep(2)
    assert {d.name for d in deployments} >= {"nightly", "ingest", "capture", "export", "train"}
    assert nightly.global_concurrency_limit and nightly.global_concurrency_limit.limit == 1
    assert [s.schedule.cron for s in nightly.schedules] == ["0 2 * * *"]
    assert scheduled and all(r.state.name == "Scheduled" for r in scheduled)


def test_inspect_shows_every_field_of_the_night_with_its_description_and_range(
        served: dict[str, str]) -> None:
    from flows.config import NightConfig

    done = _prefect(served, "deployment", "inspect", "nightly/nightly", "--output", "json")
    assert done.returncode == 0, done.stderr
    schema = json.loads(done.stdout)["parameter_openapi_schema"]
    assert list(schema["properties"]) == ["config"]  # one parameter: the night's config
    shown = schema["definitions"]
    expected = NightConfig.model_json_schema()["$defs"]
    groups = {name: field.annotation.__name__ for name, field in NightConfig.model_fields.items()
              if name != "tolerances"}
    assert set(groups) == {"library", "capture", "inspection", "models", "thresholds",
                           "runtime"}
    for group, model in groups.items():
        fields = shown[model]["properties"]
        assert set(fields) == set(expected[model]["properties"]), group
        for name, field in fields.items():
            assert field["description"] == expected[model]["properties"][name]["description"]
            assert len(field["description"]) > 15, f"{group}.{name}"
    views = shown["CaptureOptions"]["properties"]["views_per_scene"]
    assert (views["minimum"], views["maximum"]) == (1, 125)
    assert "(allowed: 1 to 125)" in views["description"]
    assert set(shown["Tolerances"]["properties"]) == set(DEFAULT_TOLERANCES.as_dict())


def test_a_parameter_out_of_range_or_naming_nothing_fails_before_any_work(
        served: dict[str, str], small_library: Path, tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    out_of_range = _deployment_run(served, {"library": {"path": str(small_library)},
                                            "runtime": {"workspace": str(ws)},
                                            "capture": {"views_per_scene": 0}})
    said = " ".join((out_of_range.stdout + out_of_range.stderr).split())
    assert out_of_range.returncode != 0 and "Created flow run" not in said, said[-3000:]
    assert "'config.capture.views_per_scene'" in said, said[-3000:]  # refused by the form
    empty = tmp_path / "empty-library"
    empty.mkdir()
    nothing = _deployment_run(served, {"library": {"path": str(empty)},
                                       "runtime": {"workspace": str(ws)}})
    assert nothing.returncode != 0
    state = _final_state(served, nothing)
    assert "library.path" in state.message and "the night would check nothing" in state.message
    assert not ws.exists()  # no run folder, no catalog: nothing was done


def test_a_deployment_run_writes_the_report_and_a_second_night_only_reports(
        served: dict[str, str], parts_library: Path, tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    out = _run_nightly(served, parts_library, ws)
    assert "Completed" in out
    run = (ws / "runs" / "latest").resolve()
    for name in RUN_FILES:
        assert (run / name).is_file() and (run / name).stat().st_size > 0, name
    summary = json.loads((run / "summary.json").read_text())
    assert summary["ingest"]["files"] == 3 and summary["ingest"]["failed"] == 0
    categories = pd.read_csv(run / "categories.csv")
    assert {"fasteners", "couplings", "all"} <= set(categories["category"])
    assert set(pd.read_parquet(run / "pairs.parquet")["method"]) == {"ltn", "mlp", "geometric"}

    async def artifacts(client: Any) -> dict[str, tuple[str, str]]:
        return {a.key: (a.type, str(a.data)) for a in await client.read_artifacts() if a.key}

    made = _client_call(served, artifacts)
    assert made["nightly-categories"][0] == "table"
    assert made["nightly-report"][0] == "markdown"  # Prefect shows a link as Markdown
    assert (run / "report.html").as_uri() in made["nightly-report-html"][1]

    _run_nightly(served, parts_library, ws)

    async def last_tasks(client: Any) -> dict[str, str]:
        from prefect.client.schemas.filters import (
            FlowFilter,
            FlowFilterName,
            FlowRunFilter,
            FlowRunFilterId,
        )

        stages = await client.read_flow_runs(flow_filter=FlowFilter(
            name=FlowFilterName(any_=["nightly-stages"])))  # the stages run in this subflow
        flow_run = max((r for r in stages if r.start_time), key=lambda r: r.start_time)
        runs = await client.read_task_runs(flow_run_filter=FlowRunFilter(
            id=FlowRunFilterId(any_=[flow_run.id])))
        return {t.name: t.state.name for t in runs}

    states = _client_call(served, last_tasks)
    heavy = {n: s for n, s in states.items() if n.split("-")[0] in {
        "ingest", "mates", "capture", "complete", "relate"} and not n.startswith("relations")}
    assert heavy and set(heavy.values()) == {"Cached"}, states
    second = (ws / "runs" / "latest").resolve()
    assert second != run
    pd.testing.assert_frame_equal(pd.read_csv(second / "relations_summary.csv"),
                                  pd.read_csv(run / "relations_summary.csv"))


def _schedule(env: dict[str, str], cwd: Path, *argv: str, console: bool = False) -> str:
    """``mateqa schedule ...`` in ``cwd`` against the server of ``env``; its output (it must
    succeed). In this process (the console script's ``main``: a command in a process of its
    own spends 5-10 s importing what this one has), or with ``console`` the console script."""
    if console:
        done = subprocess.run([str(Path(sys.executable).with_name("mateqa")), "schedule",
                               *argv], cwd=cwd, env=env, capture_output=True, text=True,
                              timeout=300)
        assert done.returncode == 0, done.stdout + done.stderr
        return done.stdout
    import contextlib
    import io

    from conftest import served_by

    from flows.cli import main

    out, err = io.StringIO(), io.StringIO()
    with served_by(env), pytest.MonkeyPatch.context() as patch:
        patch.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(["schedule", *argv])
    assert code == 0, out.getvalue() + err.getvalue()
    return out.getvalue()


def _planned(env: dict[str, str], name: str) -> list[Any]:
    """The runs the server's scheduler planned for the deployment ``nightly/NAME``."""
    async def runs_of(client: Any) -> list[Any]:
        from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterName

        return list(await client.read_flow_runs(deployment_filter=DeploymentFilter(
            name=DeploymentFilterName(any_=[name]))))

    return [r for r in _client_call(env, runs_of) if r.state and r.state.name == "Scheduled"]


def _wait_planned(env: dict[str, str], name: str, hour: int, zone: str) -> list[Any]:
    """The planned runs of ``nightly/NAME`` once the scheduler planned them at ``hour`` in
    ``zone`` (it plans every couple of seconds in this server, every minute by default)."""
    from zoneinfo import ZoneInfo

    deadline = time.monotonic() + 120
    while True:
        runs = _planned(env, name)
        hours = {r.expected_start_time.astimezone(ZoneInfo(zone)).hour for r in runs}
        if runs and hours == {hour}:
            return runs
        assert time.monotonic() < deadline, (hours, _schedule(env, Path.cwd(), "show", name))
        time.sleep(1)


def test_a_schedule_plans_its_library_s_nights_from_its_cron_beside_another(
        served: dict[str, str], small_library: Path, shared_step_dir: Path,
        tmp_path: Path) -> None:
    """What the server's scheduler plans from ``mateqa schedule``: auto-scheduled runs of the
    shipped nightly, at the cron's hour in its time zone, with the library and the schedule's
    own workspace as the night's config (a deployment run of that config is the night of
    ``test_a_deployment_run_writes_the_report_and_a_second_night_only_reports``)."""
    tiny = tmp_path / "tiny-library" / "fasteners"
    tiny.mkdir(parents=True)
    (tiny / "washer.step").write_bytes((shared_step_dir / "fasteners/kcl_washer.step").read_bytes())
    _schedule(served, tmp_path, "add", "washers", "--library", str(tiny.parent), "--cron",
              "0 3 * * *", "--views-per-scene", "1", "--no-fail-on-threshold", console=True)
    _schedule(served, tmp_path, "add", "nights", "--library", str(small_library), "--cron",
              "0 2 * * *", "--timezone", "Europe/Berlin", "--categories", "fasteners")
    listed = _schedule(served, tmp_path, "list")
    assert "washers" in listed and "Europe/Berlin" in listed, listed
    planned = _wait_planned(served, "nights", 2, "Europe/Berlin")
    assert all(r.auto_scheduled for r in planned)  # from the cron, not by hand
    config = planned[0].parameters["config"]
    assert config["runtime"]["workspace"] == str(tmp_path / "nights")  # its own, named after it
    assert config["library"] == {"path": str(small_library), "categories": ["fasteners"]}
    washers = _wait_planned(served, "washers", 3, "UTC")[0].parameters["config"]
    assert washers["capture"] == {"views_per_scene": 1}  # only what was given
    assert washers["thresholds"] == {"fail_on_threshold": False}

    _schedule(served, tmp_path, "set", "nights", "--cron", "30 1 * * *")
    shown = _schedule(served, tmp_path, "show", "nights")
    assert "30 1 * * * (Europe/Berlin)" in shown and '"fasteners"' in shown, shown
    _wait_planned(served, "nights", 1, "Europe/Berlin")  # the 02:00 runs gone, 01:30 planned
    _schedule(served, tmp_path, "set", "washers", "--no-active")
    assert "paused" in _schedule(served, tmp_path, "show", "washers")
    assert not _planned(served, "washers")  # a paused schedule plans nothing
    _schedule(served, tmp_path, "remove", "washers")
    listed = _schedule(served, tmp_path, "list")
    assert "washers" not in listed and "nights" in listed, listed
