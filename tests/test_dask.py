"""The nightly on a real Dask cluster (a scheduler and two workers on loopback, started the
ordinary way, through prefect-dask) writes the same report as on this machine's thread pool."""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pandas as pd
import pytest
from conftest import ONE_THREAD, finish_night, free_port, start_night

pytestmark = pytest.mark.server

ROOT = Path(__file__).resolve().parents[1]
# The workers' own settings, untouched: their processes are daemonic, as on any cluster.
WORKER_ENV = {k: v for k, v in os.environ.items() if not k.startswith("DASK_")}
WORKER_ENV.update(ONE_THREAD)
COMPARED = ["completion_categories.csv", "relations_summary.csv", "assembly_mates.csv"]


@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """``dask scheduler`` and two ``dask worker`` processes (each a nanny and its daemonic
    worker process); yields the scheduler address."""
    port, log = free_port(), tmp_path_factory.mktemp("dask") / "dask.log"
    address = f"tcp://127.0.0.1:{port}"
    dask = str(Path(sys.executable).with_name("dask"))
    with log.open("wb") as out:
        procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                   "--no-dashboard"], stdout=out, stderr=subprocess.STDOUT)]
        procs += [subprocess.Popen([dask, "worker", address, "--nthreads", "1",
                                    "--no-dashboard", "--name", f"w{i}"], cwd=ROOT, env=WORKER_ENV,
                                   stdout=out, stderr=subprocess.STDOUT) for i in range(2)]
    from distributed import Client

    deadline = time.monotonic() + 120
    while True:
        try:
            with Client(address, timeout=5) as client:
                if len(client.scheduler_info()["workers"]) == 2:
                    break
        except OSError:
            pass
        assert time.monotonic() < deadline, log.read_text()
        time.sleep(1)
    yield address
    for proc in procs[::-1]:
        proc.terminate()
        proc.wait(30)


def test_the_nightly_on_dask_reports_what_the_local_runner_does(
        small_library: Path, prefect_api: dict[str, str], local_night: Path,
        dask_cluster: str, tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    finish_night(start_night(small_library, ws, prefect_api,
                            runtime={"dask_address": dask_cluster}))
    local, dask = local_night, (ws / "runs" / "latest").resolve()
    from distributed import Client

    with Client(dask_cluster, timeout=10) as client:  # both workers did some of the work
        done = client.run(lambda dask_worker: dask_worker.state.transition_counter)
        daemonic = client.run(lambda: multiprocessing.current_process().daemon)
    assert len(done) == 2 and all(n > 0 for n in done.values()), done
    assert all(daemonic.values()), daemonic  # where multiprocessing children are refused
    for name in COMPARED:
        table = pd.read_csv(local / name)
        assert len(table) > 0, name
        pd.testing.assert_frame_equal(pd.read_csv(dask / name), table, obj=name)
