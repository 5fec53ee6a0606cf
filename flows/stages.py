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
from cadio.tolerances import DEFAULT_TOLERANCES
from cadio.truth.scene_config import night_scene_config
from cadio.workspace import Workspace
from flows.config import CaptureRun, ConfigError, ExportRun, IngestRun
from flows.preflight import check_finished_run
from flows.settings import ingest_config, runtime_settings
from flows.stopping import stop_on_signal
from flows.tasks import (
    Run,
    capture_stage,
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

DEFAULT_INGEST, DEFAULT_CAPTURE, DEFAULT_EXPORT = IngestRun(), CaptureRun(), ExportRun()


@flow(name="ingest", task_runner=ThreadPoolTaskRunner(max_workers=2))  # type: ignore[arg-type]
def ingest(config: IngestRun = DEFAULT_INGEST) -> dict[str, Any]:
    """Read the library's STEP files into the workspace catalog and extract the mates of its
    assemblies; ``ingest.md`` goes into a run folder.

    Args:
        config: the library, the runtime and the tolerances (``flows.config.IngestRun``; a
            library path of null is the built-in samples).

    Returns:
        The ingest totals, the number of assemblies and failed ones, and the run folder.
    """
    with stop_on_signal():
        lib_cfg, tolerances = config.library, config.tolerances
        cfg = ingest_config(runtime_settings(config.runtime), lib_cfg.voxel_sizes, tolerances)
        run = start_run(config.runtime.workspace, tolerances)
        lib = lib_cfg.path or generate_library_task(run.workspace)
        catalog = ingest_stage(lib, run, cfg, lib_cfg.batch_size, lib_cfg.categories)
        mates = mates_stage(catalog, run, tolerances, cfg.limits)
        report = build_ingest_report(read_catalog(Path(catalog)))
        write_ingest_report(Path(run.run_dir), report)
        get_run_logger().info("ingest: %d files, %d ok, %d assemblies (%d failed)",
                              report.totals.files, report.totals.ok, len(mates),
                              sum(not m.ok for m in mates))
        return {"run_dir": run.run_dir, "ingest": asdict(report.totals), "assemblies": len(mates),
                "assemblies_failed": sum(not m.ok for m in mates)}


@flow(name="capture", task_runner=ThreadPoolTaskRunner(max_workers=2))  # type: ignore[arg-type]
def capture(config: CaptureRun = DEFAULT_CAPTURE) -> dict[str, Any]:
    """Generate the scenes of an ingested workspace and capture them, its assemblies and,
    alone, every part neither shows (each part's learning examples where it is scored); or,
    with ``capture.recordings``, read those recordings instead.

    Args:
        config: how the parts are seen, the runtime and the tolerances
            (``flows.config.CaptureRun``).

    Returns:
        Counts of scenes, captures, failed captures and frames.
    """
    with stop_on_signal():
        cap, tolerances = config.capture, config.tolerances
        run = start_run(config.runtime.workspace, tolerances)
        ws = Workspace(Path(run.workspace))
        if not ws.catalog.exists():
            raise FileNotFoundError(f"{ws.catalog}: no catalog; run the ingest flow first")
        scenes = scenes_task(str(ws.catalog), run.workspace,
                             night_scene_config(cap.seed, cap.pairs_per_relation, tolerances))
        scan_cfg = ScanConfig(views_per_scene=cap.views_per_scene, noise=cap.noise,
                              tolerances=tolerances)
        limits = ingest_config(runtime_settings(config.runtime), None, tolerances).limits
        if cap.recordings:
            captured = capture_stage(scenes, run, scan_cfg, cap.recordings)
        else:
            mates = mates_stage(str(ws.catalog), run, tolerances, limits)  # cached: ingest's
            captured = render_stage(str(ws.catalog), scenes, mates, run, scan_cfg)
        return {"scenes": scenes.scenes, "captures": len(captured),
                "failed": sum(bool(c.error) for c in captured),
                "frames": sum(c.frames for c in captured)}


@flow(name="export", task_runner=ThreadPoolTaskRunner(max_workers=2))  # type: ignore[arg-type]
def export(config: ExportRun = DEFAULT_EXPORT) -> dict[str, Any]:
    """Export the predicted mates of a finished run: per assembly an XBF document with XDE
    notes, a sidecar JSON and a CadQuery constraint script (the nightly's last stage, again).

    Args:
        config: the run, where its exports go, the checkpoints it used (named in the exports)
            and the runtime (``flows.config.ExportRun``).

    Returns:
        The path of ``index.csv`` and the number of assemblies per status.
    """
    with stop_on_signal():
        workspace = config.runtime.workspace
        problems: list[tuple[str, str]] = []
        check_finished_run(workspace, config.run, problems)
        if problems:
            raise ConfigError(problems)
        ws = Workspace(Path(workspace).resolve())
        run_dir = ws.run_dir(config.run).resolve()
        source = Run(run_id=run_dir.name, workspace=str(ws.root), run_dir=str(run_dir),
                     epoch=workspace_epoch(ws))
        models = model_digests({"relations": Path(config.models.relations or SHIPPED_RELATIONS),
                                "completion": Path(config.models.completion or SHIPPED)})
        limits = ingest_config(runtime_settings(config.runtime), None,
                               DEFAULT_TOLERANCES).limits
        index, summaries = export_stage(source, models, limits, config.out)
        status: dict[str, int] = {}
        for s in summaries:
            status[s.status] = status.get(s.status, 0) + 1
        get_run_logger().info("export: %d assemblies %s: %s", len(summaries), status, index)
        return {"index": index, "assemblies": len(summaries), "status": status}
