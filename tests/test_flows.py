"""Smoke test of the nightly flow under Prefect's test harness (a real temporary server)."""
# A real deployment run against a real local server is tested with the deployments.

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from prefect.testing.utilities import prefect_test_harness

from cadio.catalog import read_catalog


@pytest.fixture(scope="module")
def harness() -> object:
    with prefect_test_harness(server_startup_timeout=120):
        yield


def test_nightly_ingests_reports_and_caches(harness: object, tmp_path: Path,
                                            box_step: Path) -> None:
    from flows.nightly import nightly

    lib = tmp_path / "lib"
    (lib / "fasteners").mkdir(parents=True)
    (lib / "casters-wheels-trolleys").mkdir()
    shutil.copy(box_step, lib / "fasteners" / "box.step")
    (lib / "casters-wheels-trolleys" / "broken.stp").write_bytes(b"ISO-10303-21;\nHEADER;")
    ws = tmp_path / "ws"

    first = nightly(library=str(lib), workspace=str(ws), voxel_sizes=[16], batch_size=1,
                    views_per_scene=2)
    assert first["ingest"]["files"] == 2
    assert first["ingest"]["ok"] == 1 and first["ingest"]["failed"] == 1
    report = Path(first["report"]).read_text()
    assert "truncated STEP file" in report and "casters-wheels-trolleys" in report
    written = json.loads((Path(first["report"]).parent / "ingest.json").read_text())
    assert written["totals"] == first["ingest"]

    stages = first["stages"]
    assert stages["scenes"] > 0 and stages["captures"] == stages["scenes"]
    assert stages["frames"] == 2 * stages["captures"]
    assert len(list((ws / "captures").glob("*.mcap"))) == stages["captures"]

    meshes = sorted((ws / "meshes").glob("*.ply"))
    stamps = [m.stat().st_mtime_ns for m in meshes]
    second = nightly(library=str(lib), workspace=str(ws), voxel_sizes=[16], batch_size=1,
                     views_per_scene=2, captures=str(ws / "captures"))
    # unchanged files: the ingest tasks are cached on content hashes, nothing is rewritten
    assert second["ingest"] == first["ingest"]
    assert [m.stat().st_mtime_ns for m in meshes] == stamps and meshes
    assert len(read_catalog(ws / "catalog.parquet")) == 2
    # read back instead of rendered: same captures, same frames
    assert second["stages"]["captures"] == stages["captures"]
    assert second["stages"]["frames"] == stages["frames"]
