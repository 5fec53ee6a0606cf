"""The isolated worker pool survives crashes, hangs and memory exhaustion of its jobs."""

from __future__ import annotations

from sandbox_targets import misbehave

from cadio.errors import WorkerError
from cadio.sandbox import Job, Limits, run_isolated


def _run(payloads: list[str], limits: Limits) -> dict[str, object]:
    outcomes = run_isolated(misbehave, [Job(p, p) for p in payloads], limits)
    return {o.job.key: (o.error if o.error is not None else o.result) for o in outcomes}


def test_segfault_becomes_error_and_batch_goes_on() -> None:
    out = _run(["ok:a", "segfault", "ok:b", "ok:c"], Limits(seconds=60, workers=1))
    assert out["ok:a"] == "a" and out["ok:b"] == "b" and out["ok:c"] == "c"
    err = out["segfault"]
    assert isinstance(err, WorkerError)
    assert "SIGSEGV" in err.reason and err.path == "segfault"


def test_hang_is_killed_after_the_time_limit() -> None:
    out = _run(["hang", "ok:after"], Limits(seconds=2, workers=1))
    assert isinstance(out["hang"], WorkerError)
    assert "timed out after 2 s" in out["hang"].reason
    assert out["ok:after"] == "after"


def test_memory_limit_is_enforced() -> None:
    out = _run(["memory", "ok:after"], Limits(seconds=60, memory_mb=1024, workers=1))
    err = out["memory"]
    assert isinstance(err, WorkerError)
    assert "memory" in err.reason
    assert out["ok:after"] == "after"


def test_exceptions_are_reported_and_workers_run_in_parallel() -> None:
    payloads = ["raise"] + [f"ok:{i}" for i in range(6)]
    out = _run(payloads, Limits(seconds=60, workers=2))
    assert len(out) == 7
    assert "ValueError: bad payload" in str(out["raise"])
    assert [out[f"ok:{i}"] for i in range(6)] == [str(i) for i in range(6)]
