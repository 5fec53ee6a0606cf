"""The nightly flow, the main job: ingest -> mates -> scenes -> captures -> completion ->
relations -> report.

Later stages (completion, relations, export) join this same flow. Each task is one call into
the packages; the flow only fans work out in coarse batches (SQLite-backed servers struggle
with thousands of tiny task runs) and logs one line per stage. Results are cached on content
hashes: a rerun over unchanged files does no CAD work again.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, is_dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

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
from cadio.capture.scan import ScanConfig, capture_assembly, capture_batch, read_captures
from cadio.catalog import CatalogRow, read_catalog, to_frame, write_catalog
from cadio.contracts import CaptureSummary, MatesSummary, ScenesSummary
from cadio.sandbox import Limits
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances, write_tolerances
from cadio.truth.assemblies import (
    MATES_VERSION,
    AssemblyJob,
    assembly_jobs,
    extract_assembly_mates,
)
from cadio.truth.scenes import SceneConfig, build_scenes, read_scenes
from cadio.workspace import Workspace, write_json
from flows.settings import Settings, ingest_config
from models.evaluate import (
    SHIPPED,
    Scores,
    complete_parts,
    part_inputs,
    write_completion_report,
)
from models.relate import SHIPPED_RELATIONS, RelateBatch, relate_batch
from reports.relations import combine_pairs, write_relation_report
from reports.render import (
    IngestTotals,
    StageTotals,
    build_ingest_report,
    build_stage_report,
    write_ingest_report,
    write_stage_report,
)


@dataclass(frozen=True)
class Run:
    """One night: its id, workspace, report folder, and the token of the workspace's life."""

    run_id: str
    workspace: str
    run_dir: str
    epoch: str


@dataclass(frozen=True)
class NightlySummary:
    """What a nightly run returns: where its reports are and the totals of each stage."""

    run_id: str
    library: str
    workspace: str
    run_dir: str
    ingest_report: str
    stages_report: str
    completion_report: str
    relations_report: str
    ingest: IngestTotals
    stages: StageTotals


def start_run(workspace: str, tolerances: Tolerances) -> Run:
    """Create the run folder and write the tolerances the run uses beside its results."""
    ws = Workspace(Path(workspace).resolve())
    run_id = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
    run_dir = ws.run_dir(run_id)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_tolerances(run_dir / "tolerances.json", tolerances)
    return Run(run_id, str(ws.root), str(run_dir), _workspace_epoch(ws))


def _workspace_epoch(ws: Workspace) -> str:
    """A token created with the workspace: a deleted workspace never reuses cached results."""
    marker = ws.root / ".epoch"
    if not marker.exists():
        ws.root.mkdir(parents=True, exist_ok=True)
        marker.write_text(datetime.now(UTC).isoformat())
    return marker.read_text()


def _plain(value: Any) -> Any:
    """JSON form of task parameters for cache keys (dataclasses as dicts, paths as text)."""
    return asdict(value) if is_dataclass(value) and not isinstance(value, type) else str(value)


def _content_key(ctx: TaskRunContext, params: dict[str, Any]) -> str:
    """Content hashes of the files a task reads + its other parameters + workspace epoch.

    ``params["files"]`` lists the paths whose bytes matter; every other parameter is hashed
    by value (dataclasses field by field).
    """
    others = {k: v for k, v in params.items() if k != "files"}
    digest = hashlib.sha256(json.dumps(others, sort_keys=True, default=_plain).encode())
    for path in map(Path, params["files"]):
        digest.update(f"{path}\0".encode())
        digest.update(file_sha256(path).encode() if path.is_file() else b"not-a-file")
    return f"{ctx.task.name}-{digest.hexdigest()}"


# ---------------------------------------------------------------- tasks: one call each


@task(name="generate-sample-library")
def generate_library_task(workspace: str) -> str:
    """Write the built-in sample library into the workspace (once; reruns reuse it)."""
    from cadio.samples.library import generate_library

    out = Workspace(Path(workspace)).library
    generate_library(out)
    return str(out)


@task(name="ingest-batch", cache_key_fn=_content_key, persist_result=True)
def ingest_batch_task(files: list[str], categories: list[str], workspace: str, epoch: str,
                      cfg: IngestConfig, config_key: str) -> list[CatalogRow]:
    """Catalog rows of a batch of files, each read in an isolated worker (``config_key``, the
    ingest version and configuration, keys the cache)."""
    found = [Found(Path(p), c) for p, c in zip(files, categories, strict=True)]
    ws = Workspace(Path(workspace))
    return ingest_files(found, ws.root, cfg, read_catalog(ws.catalog))


@task(name="write-catalog")
def write_catalog_task(batches: list[list[CatalogRow]], workspace: str) -> str:
    """Write the catalog of every batch (duplicates across batches marked)."""
    rows = mark_duplicates(row for batch in batches for row in batch)
    path = Workspace(Path(workspace)).catalog
    write_catalog(path, to_frame(rows))
    return str(path)


@task(name="mates", cache_key_fn=_content_key, persist_result=True)
def mates_task(files: list[str], jobs: list[AssemblyJob], epoch: str, limits: Limits,
               version: str = MATES_VERSION) -> list[MatesSummary]:
    """Mates of a batch of assemblies, each in an isolated worker; one summary each
    (``version``, the mates code's, keys the cache)."""
    return list(extract_assembly_mates(jobs, limits))


@task(name="scenes")
def scenes_task(catalog: str, workspace: str, cfg: SceneConfig) -> ScenesSummary:
    """Scenes of the catalog's single parts, written to the workspace."""
    return build_scenes(read_catalog(Path(catalog)), Path(workspace), cfg)


@task(name="capture")
def capture_task(scene_ids: list[str], workspace: str, cfg: ScanConfig) -> list[CaptureSummary]:
    """Render a batch of scenes to MCAP and derive their learning inputs."""
    return capture_batch(scene_ids, Workspace(Path(workspace)), cfg)


@task(name="read-captures")
def read_captures_task(captures: str, workspace: str, cfg: ScanConfig) -> list[CaptureSummary]:
    """Learning inputs of captures recorded elsewhere (real logs)."""
    return read_captures(Path(captures), Workspace(Path(workspace)), cfg)


@task(name="capture-assemblies")
def capture_assemblies_task(jobs: list[AssemblyJob], workspace: str,
                            cfg: ScanConfig) -> list[CaptureSummary]:
    """Render a batch of assemblies (their parts as placed) and derive their inputs."""
    ws = Workspace(Path(workspace))
    return [capture_assembly(j.assembly, j.category, list(j.part_ids.values()), ws, cfg)
            for j in jobs]


@task(name="relate")
def relate_task(captures: list[str], workspace: str, relations_models: str,
                completion_models: str, out: str) -> RelateBatch:
    """Relations of every pair view of a batch of captures, by every method and input."""
    return relate_batch([Path(c) for c in captures], Workspace(Path(workspace)),
                        Path(relations_models), Path(completion_models), Path(out))


@task(name="relations-report")
def relations_report_task(run: Run, batches: list[RelateBatch]) -> str:
    """The run's relation files (pairs, summary, near-boundary, assembly mates, Markdown)."""
    failed = [f for b in batches for f in b.failed]
    notes = [f"{sum(b.pair_views for b in batches)} pair views of "
             f"{sum(b.captures for b in batches)} captures; {len(failed)} captures failed."]
    notes += [f"- {f}" for f in failed]
    pairs = combine_pairs([Path(b.path) for b in batches])
    joints = combine_pairs([Path(b.joints_path) for b in batches if b.joints_path], joints=True)
    return str(write_relation_report(Path(run.run_dir), pairs, notes, joints))


@task(name="complete")
def complete_task(folders: list[str], models_dir: str, workspace: str) -> Scores:
    """Complete and score a batch of captured parts with every method."""
    return complete_parts([Path(f) for f in folders], Path(models_dir), Workspace(Path(
        workspace)))


@task(name="completion-report")
def completion_report_task(run: Run, scores: list[Scores]) -> str:
    """The completion report of the run (``completion_parts.parquet``, categories, Markdown)."""
    return str(write_completion_report(Path(run.run_dir), scores))


@task(name="report")
def report_task(run: Run, catalog: str, mates: list[MatesSummary], scenes: str | None,
                captures: list[CaptureSummary]) -> tuple[IngestTotals, StageTotals]:
    """Write the run's reports and publish them as artifacts."""
    out = Path(run.run_dir)
    ingest = build_ingest_report(read_catalog(Path(catalog)))
    write_ingest_report(out, ingest)
    stages = build_stage_report(mates, read_scenes(Path(scenes)) if scenes else None, captures)
    write_stage_report(out, stages)
    create_markdown_artifact(key="nightly-ingest", markdown=ingest.markdown(),
                             description="Ingest report")
    create_markdown_artifact(key="nightly-stages", markdown=stages.markdown(),
                             description="Mates, scenes and captures per category")
    return ingest.totals, stages.totals


# ---------------------------------------------------------------- stages: fan-out only


def _batches(items: list[Any], size: int) -> list[list[Any]]:
    return [items[i:i + size] for i in range(0, len(items), size)]


def ingest_stage(library: str, run: Run, cfg: IngestConfig, batch_size: int) -> str:
    """Every STEP file of the library in batches of ``batch_size``; the catalog's path."""
    found = discover(Path(library))
    futures = [ingest_batch_task.submit([str(f.path) for f in b], [f.category for f in b],
                                        run.workspace, run.epoch, cfg, cfg.key())
               for b in _batches(found, batch_size)]
    return write_catalog_task([f.result() for f in futures], run.workspace)


def mates_stage(catalog: str, run: Run, tol: Tolerances, limits: Limits) -> list[MatesSummary]:
    """Mates of every assembly of the catalog, four assemblies per task."""
    jobs = assembly_jobs(read_catalog(Path(catalog)), Path(run.workspace), tol)
    futures = [mates_task.submit([j.path for j in b], b, run.epoch, limits)
               for b in _batches(jobs, 4)]
    return [m for f in futures for m in f.result()]


def complete_stage(captured: list[CaptureSummary], run: Run, models_dir: str) -> list[Scores]:
    """Every captured part completed and scored (in the first capture that shows it), twenty
    parts per task."""
    ws = Workspace(Path(run.workspace))
    folders = part_inputs([ws.root / "inputs" / Path(c.path).stem for c in captured
                           if not c.error])
    futures = [complete_task.submit(b, models_dir, run.workspace)
               for b in _batches([str(f) for f in folders], 20)]
    return [f.result() for f in futures]


def capture_stage(scenes: ScenesSummary, run: Run, cfg: ScanConfig,
                  captures: str | None) -> list[CaptureSummary]:
    """Render the scenes ten per task, or read the recordings of ``captures``."""
    if captures:
        return read_captures_task(captures, run.workspace, cfg)
    ids = read_scenes(Path(scenes.path))["scene_id"].astype(str).tolist()
    futures = [capture_task.submit(b, run.workspace, cfg) for b in _batches(ids, 10)]
    return [c for f in futures for c in f.result()]


def assembly_stage(catalog: str, mates: list[MatesSummary], run: Run,
                   cfg: ScanConfig) -> list[CaptureSummary]:
    """Capture every assembly whose mates were extracted, two per task."""
    ok = {m.assembly for m in mates if m.ok}
    jobs = [j for j in assembly_jobs(read_catalog(Path(catalog)), Path(run.workspace))
            if j.assembly in ok]
    futures = [capture_assemblies_task.submit(b, run.workspace, cfg) for b in _batches(jobs, 2)]
    return [c for f in futures for c in f.result()]


def relate_stage(captured: list[CaptureSummary], run: Run, relations_models: str,
                 completion_models: str) -> list[RelateBatch]:
    """Every capture's pair views related by every method, ten captures per task."""
    paths = [c.path for c in captured if not c.error and c.path]
    out = Path(run.run_dir) / "relations"
    futures = [relate_task.submit(b, run.workspace, relations_models, completion_models,
                                  str(out / f"batch-{i:04d}.parquet"))
               for i, b in enumerate(_batches(paths, 10))]
    return [f.result() for f in futures]


class _Stopwatch:
    """Seconds since the last lap, for the one log line of each stage."""

    def __init__(self) -> None:
        self.last = time.perf_counter()

    def lap(self) -> float:
        now = time.perf_counter()
        elapsed, self.last = now - self.last, now
        return elapsed


@flow(name="nightly", task_runner=ThreadPoolTaskRunner(max_workers=2))  # type: ignore[arg-type]
def nightly(
    library: str | None = None,
    workspace: str = "workspace",
    tolerances: Tolerances = DEFAULT_TOLERANCES,
    voxel_sizes: list[int] | None = None,
    batch_size: int = 12,
    pairs_per_relation: int = 4,
    views_per_scene: int = 8,
    noise: bool = False,
    captures: str | None = None,
    completion_models: str | None = None,
    relation_models: str | None = None,
    seed: int = 0,
    workers: int | None = None,
    file_timeout_s: float | None = None,
    file_memory_mb: int | None = None,
    max_file_mb: float | None = None,
) -> NightlySummary:
    """Ingest the library, extract assembly mates, generate scenes, capture them, report.

    Args:
        library: folder of STEP files (categories are its sub-folders); None = built-in samples.
        workspace: the workspace folder.
        tolerances: every geometric tolerance of the run (written to ``tolerances.json``).
        voxel_sizes: occupancy grid sizes to write (default 32 and 64).
        batch_size: files per ingest task.
        pairs_per_relation: scenes per relation (over all splits).
        views_per_scene: rendered views per scene (spread over the paper's 125-view circle).
        noise: switch the depth sensor noise model on.
        captures: folder of MCAP captures to read instead of rendering (real logs).
        completion_models: folder of completion checkpoints (default: the shipped ones).
        relation_models: folder of relation checkpoints (default: the shipped ones).
        seed: seed of the scene generator.
        workers, file_timeout_s, file_memory_mb, max_file_mb: CAD worker processes per task
            and per-file limits (None: the ``MATEQA_*`` settings).

    Returns:
        The run id, the paths of the report files and the totals of each stage.
    """
    log, clock = get_run_logger(), _Stopwatch()
    env = Settings()
    settings = env.model_copy(update={
        "workers": env.workers if workers is None else workers,
        "file_timeout_s": file_timeout_s or env.file_timeout_s,
        "file_memory_mb": file_memory_mb or env.file_memory_mb,
        "max_file_mb": max_file_mb or env.max_file_mb})
    cfg = ingest_config(settings, voxel_sizes, tolerances)
    run = start_run(workspace, tolerances)
    lib = library or generate_library_task(run.workspace)
    log.info("library: %s (%.1f s)", lib, clock.lap())
    catalog = ingest_stage(lib, run, cfg, batch_size)
    t = build_ingest_report(read_catalog(Path(catalog))).totals
    log.info("ingest: %d files (%d ok, %d failed, %d skipped), %d parts, %d reused (%.1f s)",
             t.files, t.ok, t.failed, t.skipped, t.parts, t.cached, clock.lap())
    mates = mates_stage(catalog, run, tolerances, cfg.limits)
    log.info("mates: %d assemblies, %d failed, %d face mates (%.1f s)", len(mates),
             sum(not m.ok for m in mates), sum(m.face_mates for m in mates), clock.lap())
    scene_cfg = SceneConfig(seed=seed, pairs_per_relation=pairs_per_relation,
                            tolerances=tolerances)
    scenes = scenes_task(catalog, run.workspace, scene_cfg)
    log.info("scenes: %d from %d parts (%.1f s)", scenes.scenes, scenes.parts, clock.lap())
    scan_cfg = ScanConfig(views_per_scene=views_per_scene, noise=noise, tolerances=tolerances)
    captured = capture_stage(scenes, run, scan_cfg, captures)
    if not captures:  # recordings stand on their own; a rendered run captures the assemblies
        captured += assembly_stage(catalog, mates, run, scan_cfg)
    log.info("captures: %d, %d failed, %d frames (%.1f s)", len(captured),
             sum(bool(c.error) for c in captured), sum(c.frames for c in captured), clock.lap())
    scores = complete_stage(captured, run, completion_models or str(SHIPPED))
    completion = completion_report_task(run, scores)
    log.info("completion: %d scores of %d examples, %d failed (%.1f s)",
             sum(len(s.parts) for s in scores), sum(len(s.registration) for s in scores),
             sum(len(s.failed) for s in scores), clock.lap())
    completion_dir = completion_models or str(SHIPPED)
    batches = relate_stage(captured, run, relation_models or str(SHIPPED_RELATIONS),
                           completion_dir)
    relations = relations_report_task(run, batches)
    log.info("relations: %d pair views, %d rows, %d captures failed (%.1f s)",
             sum(b.pair_views for b in batches), sum(b.rows for b in batches),
             sum(len(b.failed) for b in batches), clock.lap())
    ingest, stages = report_task(run, catalog, mates, scenes.path, captured)
    log.info("report: %s (%.1f s)", run.run_dir, clock.lap())
    summary = NightlySummary(
        run_id=run.run_id, library=str(lib), workspace=run.workspace, run_dir=run.run_dir,
        ingest_report=str(Path(run.run_dir) / "ingest.md"),
        stages_report=str(Path(run.run_dir) / "stages.md"), completion_report=completion,
        relations_report=relations,
        ingest=ingest, stages=stages)
    write_json(Path(run.run_dir) / "summary.json", asdict(summary))
    Workspace(Path(run.workspace)).mark_latest(run.run_id)
    return summary
