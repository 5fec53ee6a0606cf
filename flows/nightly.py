"""The nightly flow: the main job. Ingest -> mates -> scenes -> captures -> report.

Later stages (completion, relations, export) are added to this same flow. Tasks
are thin: resolve paths, call one library function, write its output, return a path or a small
summary. Tasks are coarse (a batch of files) because SQLite-backed servers struggle with
thousands of tiny task runs.
"""

from __future__ import annotations

import hashlib
import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pandas as pd
from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact
from prefect.context import TaskRunContext
from prefect.task_runners import ThreadPoolTaskRunner

from cadio.cad.ingest import (
    Found,
    IngestConfig,
    discover,
    file_sha256,
    ingest_files,
    mark_duplicates,
)
from cadio.capture.scan import ScanConfig, capture_scenes, scan_inputs
from cadio.catalog import read_catalog, to_frame, write_catalog
from cadio.errors import CaptureError
from cadio.sandbox import Job, Limits, run_isolated
from cadio.truth.scenes import (
    SceneConfig,
    generate_scenes,
    read_scene_parts,
    read_scenes,
    write_scenes,
)
from cadio.workspace import Workspace, write_json
from flows.settings import Settings, ingest_config
from reports.ingest import build_ingest_report, markdown_table
from reports.stages import captures_table, joints_table, mates_table, scenes_table


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
    from cadio.samples.library import generate_library

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


def _file_cache_key(ctx: TaskRunContext, params: dict[str, Any]) -> str:
    """Content hashes of the files a task reads + its other parameters + workspace epoch."""
    digest = hashlib.sha256(json.dumps(
        {k: v for k, v in params.items() if k != "items"}, sort_keys=True, default=str
    ).encode())
    for item in params["items"]:
        p = Path(item["path"])
        digest.update(file_sha256(p).encode() if p.is_file() else b"not-a-file")
    return f"{ctx.task.name}-{digest.hexdigest()}"


@task(name="mates", cache_key_fn=_file_cache_key, persist_result=True)
def mates_task(items: list[dict[str, Any]], workspace: str, epoch: str,
               timeout_s: float, memory_mb: int) -> list[dict[str, Any]]:
    """Mates of a batch of assemblies, each in an isolated worker; one summary per assembly."""
    jobs = [Job(item["path"], {**item, "workspace": workspace}) for item in items]
    out = []
    limits = Limits(seconds=timeout_s, memory_mb=memory_mb, workers=1)
    for outcome in run_isolated("cadio.truth.mates:mates_job", jobs, limits):
        item = outcome.job.payload
        base = {"assembly": item["assembly"], "category": item["category"],
                "source": item["path"], "seconds": outcome.seconds}
        if outcome.error is None:
            out.append({**base, **outcome.result, "status": "ok", "error": ""})
        else:
            out.append({**base, "status": "failed", "error": outcome.error.reason})
    return out


@task(name="scenes")
def scenes_task(catalog_path: str, workspace: str, pairs_per_relation: int,
                seed: int) -> dict[str, Any]:
    """Generate the scene table from the catalog's single parts; returns its path and count."""
    ws = Workspace(Path(workspace))
    parts = read_scene_parts(read_catalog(Path(catalog_path)), ws.root)
    cfg = SceneConfig(seed=seed, pairs_per_relation=pairs_per_relation)
    table = generate_scenes(parts, cfg)
    write_scenes(ws.scenes, table)
    return {"path": str(ws.scenes), "scenes": len(table), "parts": len(parts)}


@task(name="capture")
def capture_task(scene_ids: list[str], workspace: str, cfg: ScanConfig) -> list[dict[str, Any]]:
    """Render a batch of scenes to MCAP and derive their learning inputs (view 0)."""
    ws = Workspace(Path(workspace))
    scenes = read_scenes(ws.scenes)
    scenes = scenes[scenes["scene_id"].isin(scene_ids)]
    captured = capture_scenes(scenes, read_catalog(ws.catalog), ws, cfg).to_dict("records")
    for row in captured:
        if not row["error"]:
            row.update(_inputs_summary(Path(row["path"]), ws, cfg))
    return captured


@task(name="read-captures")
def read_captures_task(captures_dir: str, workspace: str, cfg: ScanConfig) -> list[dict[str, Any]]:
    """Read captures recorded elsewhere (real logs) into learning inputs; one row per file."""
    ws = Workspace(Path(workspace))
    rows = []
    for path in sorted(Path(captures_dir).rglob("*.mcap")):
        row = {"scene_id": path.stem, "path": str(path), "bytes": path.stat().st_size,
               "frames": 0, "parts": 0, "error": ""}
        row.update(_inputs_summary(path, ws, cfg))
        rows.append(row)
    return rows


def _inputs_summary(path: Path, ws: Workspace, cfg: ScanConfig) -> dict[str, Any]:
    try:
        summary = scan_inputs(path, ws, cfg)
    except CaptureError as exc:
        return {"error": exc.reason}
    return {"frames": summary["frames"], "input_parts": summary["parts"],
            "seg_mean_iou": summary.get("seg_mean_iou", float("nan"))}


def _batches(items: list[Any], size: int) -> list[list[Any]]:
    return [items[i:i + size] for i in range(0, len(items), size)]


@task(name="stage-report")
def stage_report_task(run_dir: str, mates: list[dict[str, Any]], scenes_path: str | None,
                      captures: list[dict[str, Any]]) -> dict[str, Any]:
    """Per-category tables of mates, scenes and captures: report.md, JSON and an artifact."""
    scenes = read_scenes(Path(scenes_path)) if scenes_path else None
    capture_frame = pd.DataFrame(captures)
    tables = {"mates": mates_table(mates), "joints": joints_table(mates)}
    if scenes is not None:
        tables["scenes"] = scenes_table(scenes)
        tables["captures"] = captures_table(capture_frame, scenes)
    out = Path(run_dir)
    text = "\n".join(f"## {name.capitalize()}\n\n{markdown_table(t)}\n"
                     for name, t in tables.items())
    failures = [m for m in mates if m["status"] != "ok"]
    if failures:
        text += "\n## Failed assemblies\n\n" + markdown_table(
            pd.DataFrame(failures)[["category", "source", "error"]]) + "\n"
    (out / "stages.md").write_text(text)
    write_json(out / "stages.json", {k: t.to_dict("records") for k, t in tables.items()}
               | {"captures_detail": capture_frame.to_dict("records")})
    create_markdown_artifact(key="nightly-stages", markdown=text,
                             description="Mates, scenes and captures per category")
    return {
        "assemblies": len(mates), "assemblies_failed": len(failures),
        "face_mates": int(sum(m.get("face_mates", 0) for m in mates)),
        "joints": int(sum(m.get("joints", 0) for m in mates)),
        "scenes": 0 if scenes is None else len(scenes),
        "captures": len(captures), "frames": int(sum(c.get("frames", 0) for c in captures)),
    }


@flow(name="nightly", task_runner=ThreadPoolTaskRunner(max_workers=2))  # type: ignore[arg-type]
def nightly(
    library: str | None = None,
    workspace: str = "workspace",
    voxel_sizes: list[int] | None = None,
    batch_size: int = 12,
    pairs_per_relation: int = 4,
    views_per_scene: int = 8,
    noise: bool = False,
    captures: str | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Ingest the library, extract assembly mates, generate scenes, capture them, report.

    Args:
        library: folder of STEP files (categories are its sub-folders); None = built-in samples.
        workspace: the workspace folder.
        voxel_sizes: occupancy grid sizes to write (default 32 and 64).
        batch_size: files per ingest task.
        pairs_per_relation: scenes per relation (over all splits).
        views_per_scene: rendered views per scene (spread over the paper's 125-view circle).
        noise: switch the depth sensor noise model on.
        captures: folder of MCAP captures to read instead of rendering (real logs).
        seed: seed of the scene generator.

    Returns:
        A small summary: run id, paths of the report files, totals per stage.
    """
    logger = get_run_logger()
    settings = Settings()
    ws = Workspace(Path(workspace).resolve())
    run_id = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    run_dir = ws.run_dir(run_id)
    cfg = ingest_config(settings, voxel_sizes)
    lib = library or generate_library_task(str(ws.root))
    found = discover_task(lib)
    epoch = _workspace_epoch(ws)
    futures = [
        ingest_batch_task.submit(b, str(ws.root), cfg.key(), epoch, cfg)
        for b in _batches(found, batch_size)
    ]
    catalog = write_catalog_task([f.result() for f in futures], str(ws.root))
    totals = ingest_report_task(catalog, str(run_dir))
    logger.info("ingest: %s", json.dumps(totals))

    assemblies = _assembly_items(read_catalog(Path(catalog)))
    mate_futures = [mates_task.submit(b, str(ws.root), epoch, settings.file_timeout_s,
                                      settings.file_memory_mb)
                    for b in _batches(assemblies, 4)]
    mates = [m for f in mate_futures for m in f.result()]

    scan_cfg = ScanConfig(views_per_scene=views_per_scene, noise=noise,
                          grid_sizes=cfg.voxel_sizes, grid_margin=cfg.voxel_margin)
    scenes = scenes_task(catalog, str(ws.root), pairs_per_relation, seed)
    if captures:
        captured = read_captures_task(captures, str(ws.root), scan_cfg)
    else:
        ids = read_scenes(Path(scenes["path"]))["scene_id"].tolist()
        capture_futures = [capture_task.submit(b, str(ws.root), scan_cfg)
                           for b in _batches(ids, 10)]
        captured = [c for f in capture_futures for c in f.result()]
    stages = stage_report_task(str(run_dir), mates, scenes["path"], captured)
    logger.info("stages: %s", json.dumps(stages))
    summary = {"run_id": run_id, "library": str(lib), "workspace": str(ws.root),
               "report": str(run_dir / "ingest.md"), "stages_report": str(run_dir / "stages.md"),
               "ingest": totals, "stages": stages}
    write_json(run_dir / "summary.json", summary)
    return summary


def _assembly_items(catalog: pd.DataFrame) -> list[dict[str, Any]]:
    """Files with several ok solids: their path, category, name and part ids by solid index."""
    ok = catalog[(catalog["status"] == "ok") & (catalog["n_solids"] > 1)]
    items = []
    for source, rows in ok.groupby("source", sort=True):
        items.append({
            "path": str(source), "category": str(rows["category"].iloc[0]),
            "assembly": Path(str(source)).stem,
            "part_ids": {int(i): str(p) for i, p in zip(rows["solid_index"], rows["part_id"],
                                                         strict=True)},
        })
    return items

