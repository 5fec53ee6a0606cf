"""A flow stops on the first SIGTERM (or Ctrl-C): at once, with its flow runs marked.

Left to Prefect, a SIGTERM becomes an exception in the flow's thread, and the thread pool then
waits for every running task before the run is marked: a task waits on CAD workers whose
per-file limit is minutes, so the first SIGTERM was ignored for as long as the slowest batch
took (729 s once) and the run showed Running all along. Inside ``stop_on_signal`` the first
SIGTERM or SIGINT instead marks every flow run of this process Crashed (their running task
runs too), then kills the CAD worker processes and ends the process in one step, with no
thread running in between: no task can finish on a killed worker (its rows would be cached as
failures), every file is written atomically so nothing half-written is kept, and the next
night reuses what the cached tasks finished.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any
from uuid import UUID

from cadio.sandbox import kill_workers
from flows.logs import run_logger

log = logging.getLogger(__name__)

SIGNALS = (signal.SIGTERM, signal.SIGINT)
# Flow runs of this process inside ``stop_on_signal``, outermost first.
_RUNS: list[UUID] = []


@contextmanager
def stop_on_signal() -> Iterator[None]:
    """Within a flow's body: the first SIGTERM or SIGINT stops the process as described above.

    Outside the main thread (signals are delivered there only) it does nothing.
    """
    from prefect.context import FlowRunContext

    ctx = FlowRunContext.get()
    run_id = ctx.flow_run.id if ctx is not None and ctx.flow_run is not None else None
    if threading.current_thread() is not threading.main_thread() or run_id is None:
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in SIGNALS}
    _RUNS.append(run_id)
    for sig in SIGNALS:
        signal.signal(sig, _stop)
    try:
        yield
    finally:
        _RUNS.remove(run_id)
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _stop(signum: int, frame: FrameType | None) -> None:
    for sig in SIGNALS:  # the stop is under way: a second signal must not interrupt it
        signal.signal(sig, signal.SIG_IGN)
    name = signal.Signals(signum).name
    reason = f"stopped by {name}: the night ended at once (rerun to resume from its cache)"
    run_logger(__name__).warning("%s: marking %d flow run(s) Crashed and stopping the CAD "
                                 "workers", name, len(_RUNS))
    try:
        from prefect.client.orchestration import get_client

        with get_client(sync_client=True) as client:
            mark_crashed(client, list(_RUNS), reason)
    except Exception as exc:  # the server may be what is going away: stop all the same
        log.error("could not mark the flow runs: %s", exc)
    _flush_logs()
    kill_workers()  # the CAD workers of running tasks
    os._exit(128 + signum)


def mark_crashed(client: Any, runs: list[UUID], reason: str) -> None:
    """Set each flow run, and its task runs still running, to Crashed (``client``: Prefect's
    synchronous client)."""
    from prefect.client.schemas.filters import (
        FlowRunFilter,
        FlowRunFilterId,
        TaskRunFilter,
        TaskRunFilterState,
        TaskRunFilterStateType,
    )
    from prefect.client.schemas.objects import StateType
    from prefect.states import Crashed

    for run_id in reversed(runs):  # innermost first, as Prefect itself ends them
        tasks = client.read_task_runs(
            flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[run_id])),
            task_run_filter=TaskRunFilter(state=TaskRunFilterState(
                type=TaskRunFilterStateType(any_=[StateType.RUNNING, StateType.PENDING]))))
        for task_run in tasks:
            client.set_task_run_state(task_run.id, Crashed(message=reason), force=True)
        client.set_flow_run_state(run_id, Crashed(message=reason), force=True)


def _flush_logs() -> None:
    from prefect.logging.handlers import APILogWorker

    try:
        APILogWorker.drain_all(timeout=5)
    except Exception as exc:  # logs are a courtesy here; the states are already set
        log.error("could not send the last logs: %s", exc)
