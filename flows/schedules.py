"""A library's night, every night: schedules as Prefect deployments of the nightly flow.

A schedule is a name, a cron with its time zone, and the night's configuration
(``flows.config.ScheduledNight``). It lives on the Prefect server as the deployment
``nightly/<name>``: the shipped ``nightly`` deployment of ``prefect.yaml`` (its entry point, work
pool, concurrency limit and job variables) with the schedule's cron and the night's
configuration as its ``config`` parameter, tagged ``mateqa-schedule`` so that the schedules are
told apart from the shipped deployments. So a schedule is run by the worker that ``mateqa
serve`` (or the compose file, or the systemd unit) keeps up, shows in the UI like any
deployment, and runs now with ``prefect deployment run nightly/<name>``.

Several libraries side by side: each schedule has its own workspace (a folder named after it
unless given), so its catalog, caches and run history (``runs/``, the trends, ``runs/latest``)
are its own. The parameter holds only the fields the schedule sets, paths made absolute (the
worker runs elsewhere); every other field takes the default written once in its configuration.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from flows.config import NightConfig, ScheduledNight, validated

if TYPE_CHECKING:
    from uuid import UUID

    from prefect.client.orchestration import PrefectClient
    from prefect.client.schemas.objects import FlowRun
    from prefect.client.schemas.responses import DeploymentResponse

TAG = "mateqa-schedule"
FLOW = "nightly"  # the flow every schedule runs; its deployment in prefect.yaml is the template
# Fields that name files: made absolute when a schedule is written, as the worker's folder is
# not the one the schedule was written from.
PATH_FIELDS = ("library.path", "capture.recordings", "models.completion", "models.relations",
               "thresholds.file", "runtime.workspace")
T = TypeVar("T")


class ScheduleError(RuntimeError):
    """A schedule command that the server cannot carry out; the message says why and what to do."""


@dataclass(frozen=True)
class Schedule:
    """A schedule as the server holds it.

    config: the night's fields the schedule sets (nested, as ``NightConfig`` takes them); every
    other field is its default. next_run: the next start the scheduler planned ('' when none:
    paused, or not planned yet). last_run: the state and start of the newest run that was not
    merely scheduled ('' before the first).
    """

    name: str
    cron: str
    timezone: str
    active: bool
    config: dict[str, Any]
    next_run: str = ""
    last_run: str = ""

    @property
    def workspace(self) -> str:
        return str(self.config.get("runtime", {}).get("workspace", ""))

    @property
    def library(self) -> str:
        return str(self.config.get("library", {}).get("path") or "(the built-in samples)")

    def scheduled_night(self) -> ScheduledNight:
        """The schedule as the configuration it was written from."""
        when = {"name": self.name, "cron": self.cron, "timezone": self.timezone,
                "active": self.active}
        return validated(ScheduledNight, {**self.config, "schedule": when})


def night_values(config: ScheduledNight, base: Path) -> dict[str, Any]:
    """What a schedule's ``config`` parameter holds: the night's fields set in ``config``, the
    paths among them resolved against ``base``, and the workspace (``base/<name>`` unless set).
    """
    values = config.model_dump(mode="json", exclude_unset=True, exclude={"schedule"})
    values.setdefault("runtime", {}).setdefault("workspace", config.schedule.name)
    for path in PATH_FIELDS:
        group, name = path.split(".")
        value = values.get(group, {}).get(name)
        if value:
            values[group][name] = str((base / Path(value).expanduser()).resolve())
    return values


def merged(stored: Mapping[str, Any], given: Mapping[str, Any]) -> dict[str, Any]:
    """``stored`` with the groups of ``given`` laid over it, field by field."""
    out = {k: dict(v) if isinstance(v, Mapping) else v for k, v in stored.items()}
    for key, value in given.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), dict):
            out[key].update(value)
        else:
            out[key] = value
    return out


def updated(schedule: Schedule, given: ScheduledNight, base: Path) -> ScheduledNight:
    """The schedule with the fields ``given`` sets (by ``mateqa schedule set``) changed."""
    when = given.schedule.model_dump(exclude_unset=True)
    night = night_values(given, base) if given.model_fields_set - {"schedule"} else {}
    if "runtime" in night and "workspace" not in given.runtime.model_fields_set:
        del night["runtime"]["workspace"]  # a workspace not given stays the schedule's
    values = merged(schedule.config, night)
    current = schedule.scheduled_night().schedule.model_dump()
    return validated(ScheduledNight, {**values, "schedule": {**current, **when}})


def template(root: Path) -> dict[str, Any]:
    """The nightly deployment of ``root/prefect.yaml``, its work pool's aliases resolved.

    Raises:
        ScheduleError: the file or the deployment is missing.
    """
    import yaml

    path = root / "prefect.yaml"
    try:
        spec = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ScheduleError(f"cannot read {path}: {exc}") from exc
    for deployment in spec.get("deployments") or []:
        if deployment.get("name") == FLOW:
            return dict(deployment)
    raise ScheduleError(f"{path} has no deployment named {FLOW!r} to schedule")


def run(api_url: str, fn: Callable[[PrefectClient], Awaitable[T]]) -> T:
    """``fn(client)`` against the Prefect API at ``api_url``."""
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL, temporary_settings

    async def call() -> T:
        async with get_client() as client:
            return await fn(client)

    with temporary_settings({PREFECT_API_URL: api_url}):
        return asyncio.run(call())


async def apply(client: PrefectClient, config: ScheduledNight, values: dict[str, Any],
                root: Path) -> list[str]:
    """Create or replace the deployment ``nightly/<name>`` of a schedule (its future runs are
    planned afresh); returns warnings (no worker polls the pool: the night would not start).

    Raises:
        ScheduleError: the work pool does not exist on the server.
    """
    from prefect.client.schemas.actions import DeploymentScheduleCreate
    from prefect.client.schemas.schedules import CronSchedule
    from prefect.exceptions import ObjectNotFound
    from prefect.utilities.callables import parameter_schema

    from flows.nightly import nightly

    spec = template(root)
    pool = spec["work_pool"]
    try:
        await client.read_work_pool(pool["name"])
    except ObjectNotFound:
        raise ScheduleError(f"the server has no work pool {pool['name']!r}, so no night would "
                            "start: run `mateqa serve` (it creates the pool and a worker), "
                            "then add the schedule again") from None
    when = config.schedule
    await client.create_deployment(
        flow_id=await client.create_flow_from_name(FLOW), name=when.name,
        entrypoint=spec["entrypoint"], path=str(root),
        pull_steps=[{"prefect.deployments.steps.set_working_directory": {
            "directory": str(root)}}],
        parameters={"config": values}, parameter_openapi_schema=parameter_schema(
            nightly).model_dump_for_openapi(), enforce_parameter_schema=True,
        schedules=[DeploymentScheduleCreate(
            schedule=CronSchedule(cron=when.cron, timezone=when.timezone),
            active=when.active)],
        concurrency_limit=spec.get("concurrency_limit"), tags=[*spec.get("tags", []), TAG],
        description=f"{FLOW} of {values.get('library', {}).get('path') or 'the built-in samples'}"
        f" into {values['runtime']['workspace']} (mateqa schedule)",
        work_pool_name=pool["name"], work_queue_name=pool.get("work_queue_name"),
        job_variables=pool.get("job_variables") or {})
    workers = await client.read_workers_for_work_pool(pool["name"])
    if not any(str(w.status).upper().endswith("ONLINE") for w in workers):
        return [f"no worker polls the work pool {pool['name']!r} now: the night starts once one "
                "does (`mateqa serve` runs one)"]
    return []


async def read_schedules(client: PrefectClient, name: str | None = None) -> list[Schedule]:
    """Every schedule on the server (the one named, when given), by name."""
    from prefect.client.schemas.filters import (
        DeploymentFilter,
        DeploymentFilterName,
        DeploymentFilterTags,
        FlowFilter,
        FlowFilterName,
    )

    found = await client.read_deployments(
        flow_filter=FlowFilter(name=FlowFilterName(any_=[FLOW])),
        deployment_filter=DeploymentFilter(
            tags=DeploymentFilterTags(all_=[TAG]),
            name=DeploymentFilterName(any_=[name]) if name else None))
    return sorted([await _schedule(client, d) for d in found], key=lambda s: s.name)


async def _schedule(client: PrefectClient, deployment: DeploymentResponse) -> Schedule:
    planned = await _runs(client, deployment.id, scheduled=True)
    done = await _runs(client, deployment.id, scheduled=False)
    cron = deployment.schedules[0] if deployment.schedules else None
    last = done[0] if done else None
    return Schedule(
        name=deployment.name, cron=str(getattr(cron.schedule, "cron", "")) if cron else "",
        timezone=str(getattr(cron.schedule, "timezone", "") or "UTC") if cron else "",
        active=bool(cron and cron.active),
        config=dict(deployment.parameters.get("config") or {}),
        next_run=_when(planned[0].expected_start_time) if planned else "",
        last_run=f"{last.state.name} {_when(last.start_time or last.expected_start_time)}"
        if last and last.state else "")


async def _runs(client: PrefectClient, deployment: UUID, scheduled: bool) -> list[FlowRun]:
    """The deployment's next planned run (``scheduled``), or its newest other run."""
    from prefect.client.schemas.filters import (
        DeploymentFilter,
        DeploymentFilterId,
        FlowRunFilter,
        FlowRunFilterState,
        FlowRunFilterStateType,
    )
    from prefect.client.schemas.objects import StateType
    from prefect.client.schemas.sorting import FlowRunSort

    kind = [StateType.SCHEDULED]
    states = FlowRunFilterStateType(any_=kind) if scheduled else \
        FlowRunFilterStateType(not_any_=kind)
    return await client.read_flow_runs(
        deployment_filter=DeploymentFilter(id=DeploymentFilterId(any_=[deployment])),
        flow_run_filter=FlowRunFilter(state=FlowRunFilterState(type=states)),
        sort=FlowRunSort.EXPECTED_START_TIME_ASC if scheduled
        else FlowRunSort.EXPECTED_START_TIME_DESC, limit=1)


def _when(moment: Any) -> str:
    return "" if moment is None else moment.strftime("%Y-%m-%d %H:%M %Z")


async def remove(client: PrefectClient, name: str) -> bool:
    """Delete the schedule's deployment and its planned runs; False when there is none. Its
    workspace, with the reports of every night it ran, stays."""
    if not await read_schedules(client, name):
        return False
    deployment = await client.read_deployment_by_name(f"{FLOW}/{name}")
    await client.delete_deployment(deployment.id)
    return True


def check_night(config: ScheduledNight) -> list[str]:
    """What ``flows.preflight.check_night`` says of the night a schedule runs (warnings).

    Raises:
        ConfigError: the night would fail at its start (named fields).
    """
    from flows.preflight import check_night as preflight

    night: NightConfig = config.night()
    return preflight(night)
