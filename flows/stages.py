"""Flows for single stages, deployed beside the nightly: ``ingest`` (library -> catalog and
ground-truth mates), ``capture`` (catalog -> scenes -> RGB-D captures and their inputs) and
``export`` (a run's predicted mates -> XBF notes, sidecar JSON, CadQuery script).

They run the same tasks as the nightly, with the same content-hash caches, so an ``ingest``
run followed by the nightly does the CAD work once.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger
from prefect.task_runners import ThreadPoolTaskRunner

from cadio.capture.scan import ScanConfig
from cadio.catalog import read_catalog
from cadio.export.job import model_digests
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.scene_config import night_scene_config
from cadio.workspace import Workspace
from flows.config import ConfigError, Count, Views, VoxelSide
from flows.preflight import check_finished_run
from flows.settings import ingest_config, load_settings
from flows.stopping import stop_on_signal
from flows.tasks import (
    Run,
    export_stage,
    generate_library_task,
    ingest_stage,
    mates_stage,
    render_stage,
    scenes_task,
    start_run,
    workspace_epoch,
)
from models.evaluate import SHIPPED
from models.relate import SHIPPED_RELATIONS
from reports.render import build_ingest_report, write_ingest_report


@flow(name="ingest", task_runner=ThreadPoolTaskRunner(max_workers=2))  # type: ignore[arg-type]
def ingest(library: str | None = None, workspace: str = "workspace",
           categories: list[str] | None = None,
           tolerances: Tolerances = DEFAULT_TOLERANCES,
           voxel_sizes: list[VoxelSide] | None = None,
           batch_size: Count = 12) -> dict[str, Any]:
    """Read the library's STEP files into the workspace catalog and extract the mates of its
    assemblies; ``ingest.md`` goes into a run folder.

    Args:
        library: folder of STEP files (categories are its sub-folders) or a CSV listing them
            (columns path, category); None = the built-in samples.
        workspace: the workspace folder.
        categories: only these categories of the library (None: all).
        tolerances: every geometric tolerance (written beside the results).
        voxel_sizes: occupancy grid sizes to write (default 32 and 64).
        batch_size: files per ingest task.

    Returns:
        The ingest totals, the number of assemblies and failed ones, and the run folder.
    """
    with stop_on_signal():
        cfg = ingest_config(load_settings(), voxel_sizes, tolerances)
        run = start_run(workspace, tolerances)
        lib = library or generate_library_task(run.workspace)
        catalog = ingest_stage(lib, run, cfg, batch_size, categories)
        mates = mates_stage(catalog, run, tolerances, cfg.limits)
        report = build_ingest_report(read_catalog(Path(catalog)))
        write_ingest_report(Path(run.run_dir), report)
        get_run_logger().info("ingest: %d files, %d ok, %d assemblies (%d failed)",
                              report.totals.files, report.totals.ok, len(mates),
                              sum(not m.ok for m in mates))
        return {"run_dir": run.run_dir, "ingest": asdict(report.totals), "assemblies": len(mates),
                "assemblies_failed": sum(not m.ok for m in mates)}


@flow(name="capture", task_runner=ThreadPoolTaskRunner(max_workers=2))  # type: ignore[arg-type]
def capture(workspace: str = "workspace", tolerances: Tolerances = DEFAULT_TOLERANCES,
            pairs_per_relation: Count = 4, views_per_scene: Views = 8, noise: bool = False,
            seed: int = 0) -> dict[str, Any]:
    """Generate the scenes of an ingested workspace and capture them, its assemblies and,
    alone, every part neither shows (each part's learning examples where it is scored).

    Args:
        workspace: a workspace the ``ingest`` flow (or the nightly) filled.
        tolerances: every geometric tolerance (labels of the scenes).
        pairs_per_relation: scenes per relation.
        views_per_scene: rendered views per scene.
        noise: switch the depth sensor noise model on.
        seed: seed of the scene generator.

    Returns:
        Counts of scenes, captures, failed captures and frames.
    """
    with stop_on_signal():
        run = start_run(workspace, tolerances)
        ws = Workspace(Path(run.workspace))
        if not ws.catalog.exists():
            raise FileNotFoundError(f"{ws.catalog}: no catalog; run the ingest flow first")
        scene_cfg = night_scene_config(seed, pairs_per_relation, tolerances)
        scenes = scenes_task(str(ws.catalog), run.workspace, scene_cfg)
        scan_cfg = ScanConfig(views_per_scene=views_per_scene, noise=noise, tolerances=tolerances)
        mates = mates_stage(str(ws.catalog), run, tolerances,  # cached: the ingest's own results
                            ingest_config(load_settings(), None, tolerances).limits)
        captured = render_stage(str(ws.catalog), scenes, mates, run, scan_cfg)
        return {"scenes": scenes.scenes, "captures": len(captured),
                "failed": sum(bool(c.error) for c in captured),
                "frames": sum(c.frames for c in captured)}



@flow(name="export", task_runner=ThreadPoolTaskRunner(max_workers=2))  # type: ignore[arg-type]
def export(workspace: str = "workspace", run: str = "latest", out: str | None = None,
           relation_models: str | None = None,
           completion_models: str | None = None) -> dict[str, Any]:
    """Export the predicted mates of a finished run: per assembly an XBF document with XDE
    notes, a sidecar JSON and a CadQuery constraint script (the nightly's last stage, again).

    Args:
        workspace: the workspace of the run.
        run: the run id, or "latest".
        out: folder for the exports (default: the run's ``exports/``).
        relation_models, completion_models: the checkpoints the run used (default: the
            shipped ones), named in the exports.

    Returns:
        The path of ``index.csv`` and the number of assemblies per status.
    """
    with stop_on_signal():
        problems: list[tuple[str, str]] = []
        check_finished_run(workspace, run, problems)
        if problems:
            raise ConfigError(problems)
        ws = Workspace(Path(workspace).resolve())
        run_dir = ws.run_dir(run).resolve()
        source = Run(run_id=run_dir.name, workspace=str(ws.root), run_dir=str(run_dir),
                     epoch=workspace_epoch(ws))
        models = model_digests({"relations": Path(relation_models or SHIPPED_RELATIONS),
                                "completion": Path(completion_models or SHIPPED)})
        limits = ingest_config(load_settings(), None, DEFAULT_TOLERANCES).limits
        index, summaries = export_stage(source, models, limits, out)
        status: dict[str, int] = {}
        for s in summaries:
            status[s.status] = status.get(s.status, 0) + 1
        get_run_logger().info("export: %d assemblies %s: %s", len(summaries), status, index)
        return {"index": index, "assemblies": len(summaries), "status": status}
