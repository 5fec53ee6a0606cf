"""The nightly flow: the main job. Ingest the library, then report.

Later stages (mates, captures, completion, relations, export) are added to this same flow. Tasks
are thin: resolve paths, call one library function, write its output, return a path or a small
summary. Tasks are coarse (a batch of files) because SQLite-backed servers struggle with
thousands of tiny task runs.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact
from prefect.context import TaskRunContext
from prefect.task_runners import ThreadPoolTaskRunner

from cadio.catalog import read_catalog, to_frame, write_catalog
from cadio.ingest import Found, IngestConfig, discover, file_sha256, ingest_files, mark_duplicates
from cadio.sandbox import Limits
from cadio.workspace import Workspace, write_json
from flows.settings import Settings
from reports.ingest import build_ingest_report


def _workspace_epoch(ws: Workspace) -> str:
    """A token created with the workspace: a deleted workspace never reuses cached results."""
    marker = ws.root / ".epoch"
    if not marker.exists():
        ws.root.mkdir(parents=True, exist_ok=True)
        marker.write_text(datetime.now(UTC).isoformat())
    return marker.read_text()


def _batch_cache_key(ctx: TaskRunContext, params: dict[str, Any]) -> str:
    """Content hashes of the batch's files + ingest config + workspace epoch."""
    digest = hashlib.sha256()
    digest.update(params["config_key"].encode())
    digest.update(params["epoch"].encode())
    for path, category in params["batch"]:
        p = Path(path)
        digest.update(f"{path}\0{category}\0".encode())
        digest.update(file_sha256(p).encode() if p.is_file() else b"not-a-file")
    return f"ingest-batch-{digest.hexdigest()}"


@task(name="generate-sample-library")
def generate_library_task(workspace: str) -> str:
    """Write the built-in sample library into the workspace (once; reruns reuse it)."""
    from cadio.samples import generate_library

    out = Workspace(Path(workspace)).library
    paths = generate_library(out)
    get_run_logger().info("sample library: %d STEP files in %s", len(paths), out)
    return str(out)


@task(name="discover")
def discover_task(library: str) -> list[tuple[str, str]]:
    """Every STEP path under the library with its category."""
    return [(str(f.path), f.category) for f in discover(Path(library))]


@task(name="ingest-batch", cache_key_fn=_batch_cache_key, persist_result=True)
def ingest_batch_task(
    batch: list[tuple[str, str]], workspace: str, config_key: str, epoch: str, cfg: IngestConfig
) -> list[dict[str, Any]]:
    """Ingest a batch of files in isolated workers; returns catalog rows."""
    assert config_key == cfg.key()
    ws = Workspace(Path(workspace))
    found = [Found(Path(p), c) for p, c in batch]
    rows = ingest_files(found, ws.root, cfg, read_catalog(ws.catalog))
    failed = sum(r["status"] != "ok" for r in rows)
    get_run_logger().info("batch of %d files: %d rows, %d not ok", len(batch), len(rows), failed)
    return rows


@task(name="write-catalog")
def write_catalog_task(batches: list[list[dict[str, Any]]], workspace: str) -> str:
    rows = mark_duplicates([row for batch in batches for row in batch])
    path = Workspace(Path(workspace)).catalog
    write_catalog(path, to_frame(rows))
    return str(path)


@task(name="ingest-report")
def ingest_report_task(catalog_path: str, run_dir: str) -> dict[str, Any]:
    """Write the ingest report (Markdown + JSON) and publish it as an artifact."""
    report = build_ingest_report(read_catalog(Path(catalog_path)))
    out = Path(run_dir)
    out.mkdir(parents=True, exist_ok=True)
    text = report.markdown()
    (out / "ingest.md").write_text(text)
    write_json(out / "ingest.json", {
        "totals": report.totals,
        "per_category": report.per_category.to_dict("records"),
        "problems": report.problems.to_dict("records"),
    })
    create_markdown_artifact(key="nightly-ingest", markdown=text, description="Ingest report")
    return report.totals


def _batches(items: list[tuple[str, str]], size: int) -> list[list[tuple[str, str]]]:
    return [items[i:i + size] for i in range(0, len(items), size)]


@flow(name="nightly", task_runner=ThreadPoolTaskRunner(max_workers=2))  # type: ignore[arg-type]
def nightly(
    library: str | None = None,
    workspace: str = "workspace",
    voxel_sizes: list[int] | None = None,
    batch_size: int = 12,
) -> dict[str, Any]:
    """Ingest the library (the built-in sample library by default) and report.

    Args:
        library: folder of STEP files (categories are its sub-folders); None = built-in samples.
        workspace: the workspace folder.
        voxel_sizes: occupancy grid sizes to write (default 32 and 64).
        batch_size: files per ingest task.

    Returns:
        A small summary: run id, paths of the report files, totals.
    """
    logger = get_run_logger()
    settings = Settings()
    ws = Workspace(Path(workspace).resolve())
    run_id = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    cfg = _ingest_config(settings, voxel_sizes)
    lib = library or generate_library_task(str(ws.root))
    found = discover_task(lib)
    epoch = _workspace_epoch(ws)
    futures = [
        ingest_batch_task.submit(b, str(ws.root), cfg.key(), epoch, cfg)
        for b in _batches(found, batch_size)
    ]
    catalog = write_catalog_task([f.result() for f in futures], str(ws.root))
    run_dir = ws.run_dir(run_id)
    totals = ingest_report_task(catalog, str(run_dir))
    logger.info("ingest: %s", json.dumps(totals))
    summary = {"run_id": run_id, "library": str(lib), "workspace": str(ws.root),
               "report": str(run_dir / "ingest.md"), "ingest": totals}
    write_json(run_dir / "summary.json", summary)
    return summary


def _ingest_config(settings: Settings, voxel_sizes: list[int] | None) -> IngestConfig:
    workers = settings.workers or 1
    limits = Limits(seconds=settings.file_timeout_s, memory_mb=settings.file_memory_mb,
                    workers=workers)
    cfg = IngestConfig(limits=limits, max_file_mb=settings.max_file_mb)
    return replace(cfg, voxel_sizes=tuple(voxel_sizes)) if voxel_sizes else cfg
