"""Flow runs in flight on a server, and those of nights that are gone, marked Crashed.

A night killed by SIGKILL, the out-of-memory killer or a reboot cannot mark its flow runs: they
would show Running for good, and make the server look busy to whoever asks before stopping
it. So a night labels its flow runs with the host, the pid and the start time of its process
(``label_flow_run``), and whoever next asks a server which flow runs are in flight (a night
starting, ``mateqa serve``, a stop of the server) first marks Crashed those of this host whose
process is gone (``crash_dead_runs``). Runs of other hosts are left as they are: their
processes cannot be seen from here, and a run without the labels (a deployment run not yet
started, a run of another program) is never judged.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import psutil

from flows.stopping import mark_crashed

HOST, PID, PID_START = "mateqa.host", "mateqa.pid", "mateqa.pid-start"
IN_FLIGHT = ("PENDING", "RUNNING", "CANCELLING")


def label_flow_run() -> None:
    """Label the flow run this code runs in with this process (host, pid, start time)."""
    from prefect.client.orchestration import get_client
    from prefect.context import FlowRunContext

    ctx = FlowRunContext.get()
    if ctx is None or ctx.flow_run is None:
        return
    labels: dict[str, bool | int | float | str] = {
        HOST: socket.gethostname(), PID: str(os.getpid()), PID_START: _started(os.getpid())}
    with get_client(sync_client=True) as client:
        client.update_flow_run_labels(ctx.flow_run.id, labels)


def is_gone(labels: Mapping[str, Any]) -> bool:
    """Whether the labels name a process of this host that has ended (or whose pid a later
    process took)."""
    if labels.get(HOST) != socket.gethostname() or not str(labels.get(PID, "")).isdigit():
        return False
    pid = int(labels[PID])
    return not psutil.pid_exists(pid) or _started(pid) != labels.get(PID_START)


def crash_dead_runs(api_url: str | None = None) -> list[str]:
    """Mark Crashed the flow runs in flight whose process is gone (``is_gone``); their names.

    Args:
        api_url: the Prefect API (None: the one of the environment, ``PREFECT_API_URL``).
    """
    with _client(api_url) as client:
        dead = [r for r in _in_flight(client) if is_gone(r.labels)]
        if dead:
            pids = ", ".join(sorted({str(r.labels[PID]) for r in dead}))
            mark_crashed(client, [r.id for r in dead],
                         f"its process (pid {pids} on {socket.gethostname()}) is gone: the "
                         "night was killed (SIGKILL, out of memory or a reboot); run it again "
                         "to resume from its cache")
    return [r.name for r in dead]


def runs_in_flight(api_url: str | None = None) -> list[str]:
    """Names of the flow runs pending, running or cancelling, after ``crash_dead_runs``."""
    crash_dead_runs(api_url)
    with _client(api_url) as client:
        return [r.name for r in _in_flight(client)]


def _in_flight(client: Any) -> list[Any]:
    from prefect.client.schemas.filters import (
        FlowRunFilter,
        FlowRunFilterState,
        FlowRunFilterStateType,
    )
    from prefect.client.schemas.objects import StateType

    states = [StateType(s) for s in IN_FLIGHT]
    return list(client.read_flow_runs(flow_run_filter=FlowRunFilter(state=FlowRunFilterState(
        type=FlowRunFilterStateType(any_=states)))))


@contextmanager
def _client(api_url: str | None) -> Iterator[Any]:
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL, temporary_settings

    with temporary_settings({PREFECT_API_URL: api_url} if api_url else {}), \
            get_client(sync_client=True) as client:
        yield client


def _started(pid: int) -> str:
    try:
        return f"{psutil.Process(pid).create_time():.2f}"
    except psutil.Error:
        return ""
