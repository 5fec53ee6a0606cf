"""docker/compose.yaml agrees with the rest of the project (Docker cannot run on the build
machine, so the file is checked for what would break a run: shared paths, pool, settings)."""

from __future__ import annotations

from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def test_the_compose_services_share_the_workspace_and_the_pool() -> None:
    compose = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    deploy = yaml.safe_load((ROOT / "prefect.yaml").read_text())
    services = compose["services"]
    assert set(services) == {"prefect-server", "worker", "dask-scheduler", "dask-worker"}
    runners = [services[name] for name in ("worker", "dask-worker")]
    for service in runners:  # tasks pass paths: the same workspace at the same place
        assert "workspace:/app/workspace" in service["volumes"]
        env = service["environment"]
        assert env["MATEQA_WORKSPACE"] == "/app/workspace"
        assert env["DASK_DISTRIBUTED__WORKER__DAEMON"] == "False"
        assert env["MATEQA_DASK_ADDRESS"] == "tcp://dask-scheduler:8786"
    pool = deploy["deployments"][0]["work_pool"]["name"]
    assert f"--pool {pool}" in services["worker"]["command"][0]
    assert "prefect.yaml" in services["worker"]["command"][0]
    dockerfile = (ROOT / "docker" / "Dockerfile").read_text()
    for needed in ("constraints.txt", "prefect.yaml", "cadio", "models", "reports", "flows"):
        assert needed in dockerfile, needed
