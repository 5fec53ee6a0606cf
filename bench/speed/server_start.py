"""Benchmark of a local Prefect server's start on a new home: migrated afresh against started
from the kept database (``flows.server.template_database``).

Each round starts a server on a new home and a free loopback port and stops it once it answers:
first with an empty cache (Prefect migrates the empty database, and the first migrated one is
kept), then on further new homes that start from a copy of the kept one. Reported: the wall
time until ``/api/health`` answers and the CPU seconds the server process spent by then.

Usage: ``.venv/bin/python bench/speed/server_start.py [--rounds 3]``
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import tempfile
import time
from pathlib import Path

import psutil

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run from anywhere

from flows.server import start_server, stop_server, template_database


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _start(home: Path) -> tuple[float, float]:
    """(wall seconds until healthy, CPU seconds of the server process by then)."""
    clock = time.perf_counter()
    server = start_server(home, _free_port(), timeout_s=600)
    wall = time.perf_counter() - clock
    try:
        assert server.pid is not None
        proc = psutil.Process(server.pid)
        cpu = sum(t.user + t.system for t in [proc.cpu_times()] + [
            c.cpu_times() for c in proc.children(recursive=True)])
    finally:
        stop_server(server)
    return wall, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3, help="starts from the kept database")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["XDG_CACHE_HOME"] = str(Path(tmp) / "cache")
        rows = [("migrated afresh", *_start(Path(tmp) / "home-0"))]
        if not template_database().is_file():
            raise SystemExit("no database was kept after the first start")
        rows += [("from the kept database", *_start(Path(tmp) / f"home-{k}"))
                 for k in range(1, args.rounds + 1)]
    print("| start | wall s | server CPU s |\n|---|---|---|")
    for name, wall, cpu in rows:
        print(f"| {name} | {wall:.1f} | {cpu:.1f} |")


if __name__ == "__main__":
    main()
