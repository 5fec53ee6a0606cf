"""docker/compose.yaml agrees with the rest of the project and opens nothing beyond the host
without auth. Docker cannot run on the build machine, so the file is checked for what would
break a run or expose it (shared paths, pool, settings, published ports, the server's auth);
``docker compose config`` runs where Docker is installed."""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
import yaml
from conftest import free_port

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker" / "compose.yaml"
GUARD = ROOT / "docker" / "prefect-server.sh"
LOOPBACK = {"127.0.0.1", "::1", "localhost"}
PUBLISH = "MATEQA_PUBLISH_ADDRESS"


def _compose() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load(COMPOSE.read_text())
    return data


def test_the_compose_services_share_the_workspace_and_the_pool() -> None:
    compose = _compose()
    deploy = yaml.safe_load((ROOT / "prefect.yaml").read_text())
    services = compose["services"]
    assert set(services) == {"prefect-server", "worker", "dask-scheduler", "dask-worker"}
    runners = [services[name] for name in ("worker", "dask-worker")]
    for service in runners:  # tasks pass paths: the same workspace at the same place
        assert "workspace:/app/workspace" in service["volumes"]
        env = service["environment"]
        assert env["MATEQA_WORKSPACE"] == "/app/workspace"
        assert env["MATEQA_DASK_ADDRESS"] == "tcp://dask-scheduler:8786"
        assert env["PREFECT_API_AUTH_STRING"] == "${PREFECT_API_AUTH_STRING:-}"
    for name, service in services.items():  # back after a crash or a reboot
        assert service["restart"] == "unless-stopped", name
    pool = deploy["deployments"][0]["work_pool"]["name"]
    assert f"--pool {pool}" in services["worker"]["command"][0]
    assert "prefect.yaml" in services["worker"]["command"][0]
    dockerfile = (ROOT / "docker" / "Dockerfile").read_text()
    for needed in ("constraints.txt", "prefect.yaml", "cadio", "models", "reports", "flows",
                   "docker/prefect-server.sh"):
        assert needed in dockerfile, needed


def _published(spec: str | dict[str, Any]) -> tuple[str, str, str]:
    """(host address, host port, container port) of a ``ports`` entry; the address is ""
    when the entry publishes on every interface."""
    if isinstance(spec, dict):
        return (str(spec.get("host_ip", "")), str(spec.get("published", "")),
                str(spec["target"]))
    parts = re.findall(r"\$\{[^}]*\}|\[[^]]*\]|[^:]+", spec)  # ${VAR:-x}, [::1], plain
    if len(parts) == 3:
        return parts[0].strip("[]"), parts[1], parts[2]
    return "", parts[0], parts[-1]


def test_every_published_port_stays_on_this_host_unless_the_server_asks_for_auth() -> None:
    """Loopback by default; the one address a team may set is the Prefect server's, whose
    entry point then requires the auth string; the Dask scheduler is never published."""
    services = _compose()["services"]
    published = {(name, _published(p)) for name, s in services.items()
                 for p in s.get("ports", [])}
    assert {(n, port) for n, (_, _, port) in published} == {
        ("prefect-server", "4200"), ("dask-scheduler", "8787")}
    for name, (address, _, _) in published:
        variable = re.fullmatch(r"\$\{(\w+):-([^}]*)\}", address)
        if variable is None:
            assert address in LOOPBACK, (name, address)
            continue
        assert variable.groups() == (PUBLISH, "127.0.0.1"), (name, address)
        server = services[name]
        assert name == "prefect-server"
        assert server["entrypoint"][:2] == ["sh", "/app/docker/prefect-server.sh"]
        env = server["environment"]
        assert env[PUBLISH] == address  # the guard sees the address the port is published on
        assert env["PREFECT_SERVER_API_AUTH_STRING"] == "${PREFECT_API_AUTH_STRING:-}"
    scheduler = services["dask-scheduler"]["entrypoint"]
    assert scheduler[scheduler.index("--port") + 1] == "8786"


def _guard(env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """The server's entry point with ``env`` as its command: what the server would get."""
    base = {"PATH": os.environ["PATH"]}
    return subprocess.run(["sh", str(GUARD), "env"], env={**base, **env}, capture_output=True,
                          text=True, timeout=60)


@pytest.mark.parametrize(("address", "auth", "starts", "asks"), [
    (None, None, True, False),                   # compose's default: loopback, no auth
    ("127.0.0.1", "", True, False),              # unset in the shell: compose passes ""
    ("0.0.0.0", "", False, False),               # exposed without auth: refused
    ("192.168.1.20", None, False, False),
    ("0.0.0.0", "team:s3cret", True, True),      # exposed with auth: asked for
    ("127.0.0.1", "team:s3cret", True, True),
])
def test_the_server_entry_point_refuses_to_open_without_auth(
        address: str | None, auth: str | None, starts: bool, asks: bool) -> None:
    env = {k: v for k, v in ((PUBLISH, address), ("PREFECT_SERVER_API_AUTH_STRING", auth))
           if v is not None}
    proc = _guard(env)
    assert (proc.returncode == 0) == starts, proc.stderr
    if not starts:
        assert proc.returncode == 2 and "PREFECT_API_AUTH_STRING" in proc.stderr
        return
    # an empty auth string would make Prefect refuse every request: it is no auth string
    assert ("PREFECT_SERVER_API_AUTH_STRING=team:s3cret" in proc.stdout.splitlines()) == asks
    assert ("PREFECT_SERVER_API_AUTH_STRING" in proc.stdout) == asks


def test_docker_compose_config_publishes_on_loopback() -> None:
    docker = shutil.which("docker")
    plugin = docker and subprocess.run([docker, "compose", "version"], capture_output=True,
                                       timeout=60).returncode == 0
    if not plugin:
        pytest.skip("Docker Compose is not installed on this machine (no `docker compose`): "
                    "the compose file is checked as YAML above")
    env = {k: v for k, v in os.environ.items() if k not in (PUBLISH, "PREFECT_API_AUTH_STRING")}
    proc = subprocess.run([docker, "compose", "-f", str(COMPOSE), "config", "--format", "json"],
                          env=env, capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    config = json.loads(proc.stdout)
    ports = [p for s in config["services"].values() for p in s.get("ports", [])]
    assert ports and all(p["host_ip"] == "127.0.0.1" for p in ports), ports
    server = config["services"]["prefect-server"]["environment"]
    assert server[PUBLISH] == "127.0.0.1" and not server["PREFECT_SERVER_API_AUTH_STRING"]


@pytest.mark.server
def test_the_auth_string_locks_the_prefect_api(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """The settings compose passes are the ones Prefect reads: a server given
    PREFECT_SERVER_API_AUTH_STRING refuses requests without it, and Prefect's client with
    PREFECT_API_AUTH_STRING gets in."""
    from flows.server import api_url, start_server, stop_server

    monkeypatch.setenv("PREFECT_SERVER_API_AUTH_STRING", "team:s3cret")
    monkeypatch.delenv("PREFECT_API_KEY", raising=False)  # a key would take precedence
    port = free_port()
    proc = start_server(tmp_path / "home", port, timeout_s=180)  # /api/health stays open
    try:
        url = f"{api_url(port)}/flows/filter"

        def status(token: str | None) -> int:
            request = urllib.request.Request(url, data=b"{}", method="POST",
                                             headers={"Content-Type": "application/json"})
            if token is not None:
                request.add_header("Authorization", f"Basic {token}")
            try:
                with urllib.request.urlopen(request, timeout=30) as resp:
                    return int(resp.status)
            except urllib.error.HTTPError as exc:
                return exc.code

        good = base64.b64encode(b"team:s3cret").decode()
        bad = base64.b64encode(b"team:guess").decode()
        assert (status(None), status(bad), status(good)) == (401, 401, 200)
        env = {**os.environ, "PREFECT_API_URL": api_url(port), "PREFECT_HOME": str(tmp_path)}
        env.pop("PREFECT_SERVER_API_AUTH_STRING")
        ls = [sys.executable, "-m", "prefect", "flow", "ls"]
        without = subprocess.run(ls, env=env, capture_output=True, text=True, timeout=120)
        with_auth = subprocess.run(ls, env={**env, "PREFECT_API_AUTH_STRING": "team:s3cret"},
                                   capture_output=True, text=True, timeout=120)
        assert without.returncode != 0 and with_auth.returncode == 0, with_auth.stderr
    finally:
        stop_server(proc)
