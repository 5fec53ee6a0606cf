"""The tasks of mateqa's flows (one call each into the packages) and the stages that fan them
out in coarse batches (SQLite-backed servers struggle with thousands of tiny task runs).

Caching: every task that does real work is keyed on the content of what it reads (file hashes,
the rows it works on, its configuration, the registered methods' code) plus the workspace's
epoch, and persists its result. A second night over an unchanged library reuses every ingest,
mates, capture, completion and relation batch and only writes the reports. A task killed halfway
writes no cache record, and every file it writes is renamed into place only when complete, so a
rerun after a kill redoes exactly the unfinished batches and never reads a half-written file.

Retries: only transient failures are retried (the operating system ran out of something, a
connection dropped); a bad input never raises out of a task, it becomes a row of the report.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable
from dataclasses import asdict, dataclass, is_dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from prefect import task
from prefect.context import TaskRunContext
from prefect.futures import as_completed

from cadio.cad.ingest import (
    Found,
    IngestConfig,
    discover,
    file_sha256,
    ingest_files,
    mark_duplicates,
)
from cadio.capture.coverage import (
    Plan,
    alone_id,
    capture_parts_alone,
    ingested_parts,
    is_alone,
    placements,
    scoring_plan,
    unscored_parts,
)
from cadio.capture.scan import (
    ASSEMBLY_PREFIX,
    ScanConfig,
    capture_assembly,
    capture_batch,
    read_captures,
)
from cadio.catalog import CatalogRow, read_catalog, to_frame, write_catalog
from cadio.contracts import CaptureSummary, ExportSummary, MatesSummary, ScenesSummary
from cadio.disk_space import capture_need_mb, check_free_space, ingest_need_mb
from cadio.evidence.pair_features import evidence_digest
from cadio.export.job import ExportJob, export_assemblies, run_jobs, write_index
from cadio.inspect.defects import DefectPlan
from cadio.inspect.evaluate import (
    ISOLATED,
    AssemblyInspection,
    inspect_isolated,
    inspect_recording_rows,
    inspection_digest,
)
from cadio.inspect.recording import assembly_recordings
from cadio.inspect.stage import InspectConfig
from cadio.sandbox import Job, Limits, run_isolated
from cadio.tolerances import Tolerances, write_tolerances
from cadio.truth.assemblies import (
    MATES_VERSION,
    AssemblyJob,
    assembly_jobs,
    extract_assembly_mates,
)
from cadio.truth.scene_config import SceneConfig
from cadio.truth.scenes import build_scenes, read_scenes
from cadio.workspace import Workspace, atomic_path
from flows.config import InspectionOptions
from flows.logs import run_logger
from models.completions import COMPLETIONS
from models.evaluate import Scores, complete_isolated, folder_meta, part_inputs
from models.relate import (
    RelateBatch,
    RelateInspectionJob,
    reading_digest,
    relate_inspection_job,
    relate_isolated,
)
from models.relation_inputs import INPUTS
from models.relation_methods import RELATION_METHODS
from reports.methods import product
from reports.relations import pairs_frame

# Bump when a stage's code changes what it writes, so cached batches are redone.
CAPTURE_VERSION = "capture-2"
COMPLETION_VERSION = "completion-2"
RELATE_VERSION = "relate-3"


@dataclass(frozen=True)
class Run:
    """One night: its id, workspace, report folder, and the token of the workspace's life."""

    run_id: str
    workspace: str
    run_dir: str
    epoch: str


def start_run(workspace: str, tolerances: Tolerances) -> Run:
    """Create the run folder and write the tolerances the run uses beside its results."""
    ws = Workspace(Path(workspace).resolve())
    run_id = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
    run_dir = ws.run_dir(run_id)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_tolerances(run_dir / "tolerances.json", tolerances)
    return Run(run_id, str(ws.root), str(run_dir), workspace_epoch(ws))


def workspace_epoch(ws: Workspace) -> str:
    """A token created with the workspace: a deleted workspace never reuses cached results."""
    marker = ws.root / ".epoch"
    if not marker.exists():
        ws.root.mkdir(parents=True, exist_ok=True)
        marker.write_text(datetime.now(UTC).isoformat())
    return marker.read_text()


# ---------------------------------------------------------------- cache keys


def _plain(value: Any) -> Any:
    """JSON form of cache-key values (dataclasses as dicts, arrays as lists, paths as text)."""
    if is_dataclass(value) and not isinstance(value, type):
        return asdict(value)
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)


def content_digest(files: Iterable[Path | str], **values: Any) -> str:
    """SHA-256 of the named files' bytes (a missing file counts as such) and of ``values``."""
    digest = hashlib.sha256(json.dumps(values, sort_keys=True, default=_plain).encode())
    for path in map(Path, files):
        digest.update(os.fsencode(path) + b"\0")  # names need not be UTF-8
        digest.update(file_sha256(path).encode() if path.is_file() else b"not-a-file")
    return digest.hexdigest()


def _content_key(ctx: TaskRunContext, params: dict[str, Any]) -> str:
    """Content hashes of ``params["files"]`` + every other parameter by value."""
    others = {k: v for k, v in params.items() if k != "files"}
    return f"{ctx.task.name}-{content_digest(params['files'], **others)}"


def _given_key(ctx: TaskRunContext, params: dict[str, Any]) -> str:
    """The digest the stage computed (``params["key"]``): inputs already hashed once."""
    return f"{ctx.task.name}-{params['key']}"


def _transient(task: Any, task_run: Any, state: Any) -> bool:
    """Retry only what a second try can fix: resources or connections, not inputs."""
    try:
        state.result()
    except (MemoryError, ConnectionError, TimeoutError, BrokenPipeError):
        return True
    except Exception:  # anything else is not transient: no retry
        return False
    return False


_RETRY: dict[str, Any] = {"retries": 2, "retry_delay_seconds": 5,
                          "retry_condition_fn": _transient}
_CACHED: dict[str, Any] = {"cache_key_fn": _given_key, "persist_result": True, **_RETRY}


def _files_in(folders: Iterable[Path]) -> list[Path]:
    return sorted(p for f in folders if f.is_dir() for p in f.rglob("*") if p.is_file()
                  and not p.name.startswith("."))


def _models(folder: str) -> list[Path]:
    return sorted(Path(folder).glob("*.pt"))


def _categories(ws: Workspace) -> dict[str, str]:
    """Part id -> category of the catalog (the scoring stages label rows with it)."""
    catalog = read_catalog(ws.catalog)
    return dict(zip(catalog["part_id"].astype(str), catalog["category"].astype(str),
                    strict=True))


def _labels_of(categories: dict[str, str], folders: Iterable[Path]) -> list[tuple[str, str]]:
    """The categories of the parts whose examples lie in ``folders`` (input folders of one
    instance each): what a batch's rows are labelled with, and no other part's, so that a
    part added to the library redoes no batch that does not hold it."""
    parts = set()
    for folder in folders:
        meta = folder_meta(folder)
        if meta is not None:
            parts.add(str(meta["part_id"]))
    return sorted((p, categories.get(p, "")) for p in parts)


# ---------------------------------------------------------------- tasks: one call each


@task(name="generate-sample-library", **_RETRY)
def generate_library_task(workspace: str) -> str:
    """Write the built-in sample library into the workspace (once; reruns reuse it)."""
    from cadio.samples.library import generate_library

    out = Workspace(Path(workspace)).library
    generate_library(out)
    return str(out)


@task(name="ingest-batch", cache_key_fn=_content_key, persist_result=True, **_RETRY)
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


@task(name="mates", cache_key_fn=_content_key, persist_result=True, **_RETRY)
def mates_task(files: list[str], jobs: list[AssemblyJob], epoch: str, limits: Limits,
               version: str = MATES_VERSION) -> list[MatesSummary]:
    """Mates of a batch of assemblies, each in an isolated worker; one summary each
    (``version``, the mates code's, keys the cache)."""
    return list(extract_assembly_mates(jobs, limits))


@task(name="scenes", **_RETRY)
def scenes_task(catalog: str, workspace: str, cfg: SceneConfig) -> ScenesSummary:
    """Scenes of the catalog's single parts, written to the workspace."""
    return build_scenes(read_catalog(Path(catalog)), Path(workspace), cfg)


@task(name="capture", **_CACHED)
def capture_task(scene_ids: list[str], workspace: str, cfg: ScanConfig, key: str,
                 plan: Plan | None = None) -> list[CaptureSummary]:
    """Render a batch of scenes to MCAP and derive their learning inputs (examples of the
    parts ``plan`` scores in them)."""
    return capture_batch(scene_ids, Workspace(Path(workspace)), cfg, plan)


@task(name="read-captures", **_RETRY)
def read_captures_task(captures: str, workspace: str, cfg: ScanConfig) -> list[CaptureSummary]:
    """Learning inputs of captures recorded elsewhere (real logs), but the recordings of an
    assembly's own folder (the inspection reads those)."""
    ws = Workspace(Path(workspace))
    own = [p for _, p in assembly_recordings(Path(captures), library_assemblies(ws))]
    return read_captures(Path(captures), ws, cfg, skip=own)


def library_assemblies(ws: Workspace) -> set[str]:
    """The names of the library's assemblies (its files with several solids read)."""
    catalog = read_catalog(ws.catalog)
    ok = catalog[(catalog["status"] == "ok") & (catalog["n_solids"] > 1)]
    return {Path(str(s)).stem for s in ok["source"]}


@task(name="capture-assemblies", **_CACHED)
def capture_assemblies_task(jobs: list[AssemblyJob], workspace: str, cfg: ScanConfig,
                            key: str, plan: Plan | None = None) -> list[CaptureSummary]:
    """Render a batch of assemblies (their parts as placed) and derive their inputs
    (examples of the parts ``plan`` scores in them)."""
    ws = Workspace(Path(workspace))
    return [capture_assembly(j.assembly, j.category, list(j.part_ids.values()), ws, cfg,
                             None if plan is None else plan.get(ASSEMBLY_PREFIX + j.assembly, ()))
            for j in jobs]


@task(name="capture-alone", **_CACHED)
def capture_alone_task(part_ids: list[str], workspace: str, cfg: ScanConfig,
                       key: str) -> list[CaptureSummary]:
    """Render a batch of parts, each alone, and build their examples to be scored."""
    return capture_parts_alone(part_ids, Workspace(Path(workspace)), cfg)


@task(name="complete", **_CACHED)
def complete_task(folders: list[str], models_dir: str, workspace: str, key: str) -> Scores:
    """Complete and score a batch of captured parts with every method, in a worker process
    (``models.evaluate.complete_isolated``)."""
    return complete_isolated([Path(f) for f in folders], Path(models_dir), Workspace(Path(
        workspace)))


@task(name="relate", **_CACHED)
def relate_task(captures: list[str], workspace: str, relations_models: str,
                completion_models: str, out: str, key: str) -> RelateBatch:
    """Relations of every pair view of a batch of captures, by every method and input, in a
    worker process (``models.relate.relate_isolated``)."""
    return relate_isolated([Path(c) for c in captures], Workspace(Path(workspace)),
                           Path(relations_models), Path(completion_models), Path(out))


@task(name="export", **_RETRY)
def export_task(jobs: list[ExportJob], limits: Limits) -> list[ExportSummary]:
    """Sidecar JSON, XBF with notes and CadQuery script of a batch of assemblies, each in an
    isolated worker (not cached: each run writes its own exports)."""
    return list(export_assemblies(jobs, limits))


# ---------------------------------------------------------------- stages: fan-out only


def batches(items: list[Any], size: int) -> list[list[Any]]:
    """``items`` in consecutive lists of ``size``."""
    return [items[i:i + size] for i in range(0, len(items), size)]


def stable_batches(items: list[Any], size: int, name: Any = str) -> list[list[Any]]:
    """``items`` in consecutive lists of ``size`` on average, each ending at an item whose
    ``name`` hashes to a cut (one in ``size``; at most ``3 * size`` items a list): where the
    cuts fall follows the items themselves, not their count, so an item added to or removed
    from a library changes its own list, not every later one (a cached batch stays a hit)."""
    out: list[list[Any]] = []
    current: list[Any] = []
    for item in items:
        current.append(item)
        cut = int(hashlib.sha256(str(name(item)).encode()).hexdigest()[:12], 16) % size == 0
        if cut or len(current) >= 3 * size:
            out.append(current)
            current = []
    if current:
        out.append(current)
    return out


def ingest_stage(library: str, run: Run, cfg: IngestConfig, batch_size: int,
                 categories: list[str] | None = None) -> str:
    """Every STEP file of the library (of ``categories`` only, when given) in batches of
    ``batch_size``; the catalog's path. Stops first when the disk cannot hold what the files
    not yet ingested would write (``DiskSpaceError``)."""
    found = [f for f in discover(Path(library)) if not categories or f.category in categories]
    done = set(read_catalog(Workspace(Path(run.workspace)).catalog).query("status == 'ok'")
               ["source"].astype(str))
    todo = [f.path for f in found if str(f.path) not in done]
    _require_space(run, ingest_need_mb(todo), f"the {len(todo)} new STEP file(s) to ingest")
    futures = [ingest_batch_task.submit([str(f.path) for f in b], [f.category for f in b],
                                        run.workspace, run.epoch, cfg, cfg.key())
               for b in batches(found, batch_size)]
    return write_catalog_task([f.result() for f in futures], run.workspace)


def mates_stage(catalog: str, run: Run, tol: Tolerances, limits: Limits) -> list[MatesSummary]:
    """Mates of every assembly of the catalog, four assemblies per task."""
    jobs = assembly_jobs(read_catalog(Path(catalog)), Path(run.workspace), tol)
    futures = [mates_task.submit([j.path for j in b], b, run.epoch, limits)
               for b in batches(jobs, 4)]
    return [m for f in futures for m in f.result()]


def render_stage(catalog: str, scenes: ScenesSummary, mates: list[MatesSummary], run: Run,
                 cfg: ScanConfig) -> list[CaptureSummary]:
    """Render the scenes and the assemblies, a part scored in the first capture of each
    context that places it (``cadio.capture.coverage.scoring_plan``), then alone every part
    that none of them scored."""
    jobs = captured_assemblies(catalog, mates, run)
    placed = placements(read_scenes(Path(scenes.path)), jobs)
    _require_capture_space(run, placed, read_catalog(Path(catalog)), cfg)
    plan = scoring_plan(placed)
    # the assemblies first and side by side with the scenes: they are the longest tasks, and
    # a stage that waited for the scenes before starting them left a core idle at each end
    assemblies = assembly_futures(jobs, run, cfg, plan)
    captured = collect(scene_futures(scenes, run, cfg, plan)) + collect(assemblies)
    return captured + alone_stage(unscored_parts(read_catalog(Path(catalog)), captured), run,
                                  cfg)


def _require_capture_space(run: Run, placed: dict[str, list[str]], catalog: pd.DataFrame,
                           cfg: ScanConfig) -> None:
    """Stop before the captures when the disk cannot hold the ones not yet on disk: the
    scenes, the assemblies, and alone every part neither places (more may follow, for parts
    hidden in every view)."""
    ws = Workspace(Path(run.workspace))
    shown = {p for parts in placed.values() for p in parts}
    alone = [alone_id(p) for p in ingested_parts(catalog)["part_id"] if p not in shown]
    todo = [c for c in [*placed, *alone] if not ws.capture(c).is_file()]
    _require_space(run, capture_need_mb(len(todo), cfg.views_per_scene, cfg.noise),
                   f"the {len(todo)} new capture(s) of {cfg.views_per_scene} view(s)")


def _require_space(run: Run, need_mb: float, what: str) -> None:
    """Check the workspace's disk for ``what`` (``check_free_space``) and log the figures."""
    free = check_free_space(Path(run.workspace), need_mb, what)
    run_logger(__name__).info("disk: %s need about %.0f MB; %.0f MB free", what, need_mb, free)


def collect(futures: list[Any]) -> list[CaptureSummary]:
    """The summaries of submitted capture tasks, in the order submitted."""
    return [c for f in futures for c in f.result()]


def capture_stage(scenes: ScenesSummary, run: Run, cfg: ScanConfig, captures: str | None,
                  plan: Plan | None = None) -> list[CaptureSummary]:
    """Render the scenes ten per task (examples of the parts ``plan`` scores in each; None:
    of all), or read the recordings of ``captures``."""
    if captures:
        return read_captures_task(captures, run.workspace, cfg)
    return collect(scene_futures(scenes, run, cfg, plan))


def scene_futures(scenes: ScenesSummary, run: Run, cfg: ScanConfig,
                  plan: Plan | None = None) -> list[Any]:
    """The scenes' capture tasks, ten scenes each, submitted."""
    ws = Workspace(Path(run.workspace))
    table = read_scenes(Path(scenes.path))
    colours = dict(zip(*(read_catalog(ws.catalog)[c].astype(str) for c in ("part_id", "colour")),
                       strict=True))
    futures = []
    for rows in stable_batches(table.to_dict("records"), 10, lambda r: r["scene_id"]):
        ids = [str(r["scene_id"]) for r in rows]
        parts = sorted({str(r[c]) for r in rows for c in ("part_a", "part_b")})
        scored = None if plan is None else {i: plan[i] for i in ids if i in plan}
        key = content_digest(
            [ws.mesh(p) for p in parts], rows=rows, colours=[colours.get(p) for p in parts],
            cfg=cfg, epoch=run.epoch, version=CAPTURE_VERSION, plan=scored)
        futures.append(_refreshed(capture_task, _present(ws, ids)).submit(
            ids, run.workspace, cfg, key, scored))
    return futures


def _present(ws: Workspace, scene_ids: list[str]) -> bool:
    """Whether every capture of a batch and its inputs are on disk."""
    return all(ws.capture(s).is_file() and (ws.root / "inputs" / s).is_dir() for s in scene_ids)


def _refreshed(cached: Any, present: bool) -> Any:
    """The task as is when its outputs are on disk; otherwise one that recomputes and
    replaces its cache record (a cached batch whose files were deleted is redone)."""
    return cached if present else cached.with_options(refresh_cache=True)


def captured_assemblies(catalog: str, mates: list[MatesSummary], run: Run) -> list[AssemblyJob]:
    """The assemblies to capture: those whose mates were extracted."""
    ok = {m.assembly for m in mates if m.ok}
    return [j for j in assembly_jobs(read_catalog(Path(catalog)), Path(run.workspace))
            if j.assembly in ok]


def assembly_futures(jobs: list[AssemblyJob], run: Run, cfg: ScanConfig,
                     plan: Plan | None = None) -> list[Any]:
    """The assemblies' capture tasks, one assembly each (examples of the parts ``plan`` scores
    in each; None: of all), submitted: an assembly of dozens of parts is a long task alone."""
    ws = Workspace(Path(run.workspace))
    futures = []
    for b in batches(jobs, 1):
        ids = [ASSEMBLY_PREFIX + j.assembly for j in b]
        scored = None if plan is None else {i: plan[i] for i in ids if i in plan}
        files = [ws.mates(j.assembly) for j in b] + [ws.mesh(p) for j in b
                                                     for p in j.part_ids.values()]
        key = content_digest(files, jobs=b, cfg=cfg, epoch=run.epoch, version=CAPTURE_VERSION,
                             plan=scored)
        futures.append(_refreshed(capture_assemblies_task, _present(ws, ids)).submit(
            b, run.workspace, cfg, key, scored))
    return futures


# Parts per task of the stages whose tasks cost about the same each: small enough that the
# last round of two tasks does not leave a core idle for long, large enough that a task's own
# cost (a few milliseconds, and loading the checkpoints) stays small beside its work.
ALONE_BATCH, COMPLETION_BATCH = 4, 10


def alone_stage(part_ids: list[str], run: Run, cfg: ScanConfig) -> list[CaptureSummary]:
    """Capture each of the parts alone, ``ALONE_BATCH`` per task."""
    ws = Workspace(Path(run.workspace))
    catalog = read_catalog(ws.catalog)
    colours = dict(zip(catalog["part_id"].astype(str), catalog["colour"].astype(str),
                       strict=True))
    futures = []
    for b in stable_batches(part_ids, ALONE_BATCH):
        key = content_digest([ws.mesh(p) for p in b], parts=b, colours=[colours.get(p) for p in b],
                             cfg=cfg, epoch=run.epoch, version=CAPTURE_VERSION)
        present = _present(ws, [alone_id(p) for p in b])
        futures.append(_refreshed(capture_alone_task, present).submit(b, run.workspace, cfg,
                                                                       key))
    return [c for f in futures for c in f.result()]


def complete_stage(captured: list[CaptureSummary], run: Run, models_dir: str) -> list[Scores]:
    """Every scored part completed and scored (once in each context it was seen in: in the
    capture that scored it there), ``COMPLETION_BATCH`` parts per task."""
    ws = Workspace(Path(run.workspace))
    folders = part_inputs([ws.root / "inputs" / Path(c.path).stem for c in captured
                           if not c.error])
    categories = _categories(ws)
    futures = []
    for b in stable_batches(folders, COMPLETION_BATCH, lambda f: f"{f.parent.name}/{f.name}"):
        # the captures and the registration's code too: the registered completion reads them
        shown = sorted(p for p in {ws.capture(f.parent.name) for f in b} if p.is_file())
        key = content_digest([*_files_in(b), *shown, *_models(models_dir)], folders=b,
                             labels=_labels_of(categories, b), epoch=run.epoch,
                             version=COMPLETION_VERSION,
                             methods=COMPLETIONS.digest(), cad=inspection_digest())
        futures.append(complete_task.submit([str(f) for f in b], models_dir, run.workspace, key))
    return [f.result() for f in futures]


def relate_batches(paths: list[Path]) -> list[list[Path]]:
    """The relation stage's batches: each assembly capture on its own, first, then the scenes
    ten at a time. An assembly holds most of a night's pair views (every pair of its parts in
    every view), so assemblies batched together kept one task busy long after the others
    had finished, with a core idle."""
    whole = [p for p in paths if p.stem.startswith(ASSEMBLY_PREFIX)]
    return [[p] for p in whole] + stable_batches([p for p in paths if p not in whole], 10,
                                                 lambda p: p.stem)


def relate_stage(captured: list[CaptureSummary], run: Run, relations_models: str,
                 completion_models: str) -> list[RelateBatch]:
    """Every capture's pair views related by every method (``relate_batches``); each batch's
    rows are written once under ``relations/<key>.parquet`` of the workspace."""
    ws = Workspace(Path(run.workspace))
    paths = [Path(c.path) for c in captured
             if not c.error and c.path and not is_alone(c.scene_id)]  # a part alone: no pair
    categories = _categories(ws)
    futures = []
    for b in relate_batches(paths):
        folders = [ws.root / "inputs" / p.stem for p in b]
        inputs = _files_in(folders)
        labels = _labels_of(categories, [f for c in folders if c.is_dir()
                                         for f in sorted(c.iterdir()) if f.is_dir()])
        mates = [ws.mates(p.stem[len(ASSEMBLY_PREFIX):]) for p in b
                 if p.stem.startswith(ASSEMBLY_PREFIX)]
        files = [*b, *inputs, *mates, *_models(relations_models), *_models(completion_models)]
        name = content_digest(files, labels=labels, epoch=run.epoch, version=RELATE_VERSION,
                              evidence=evidence_digest(), methods=RELATION_METHODS.digest(),
                              inputs=INPUTS.digest(), reading=reading_digest())
        out = ws.root / "relations" / f"{name[:32]}.parquet"
        present = out.is_file() and out.with_name(f"{out.stem}-joints.parquet").is_file()
        futures.append(_refreshed(relate_task, present).submit(
            [str(p) for p in b], run.workspace, relations_models, completion_models, str(out),
            name))
    return [f.result() for f in futures]



def export_stage(run: Run, models: dict[str, str], limits: Limits, out: str | None = None,
                 source_run: str | None = None) -> tuple[str, list[ExportSummary]]:
    """Every assembly's predicted mates of a run (``source_run``'s folder, default this run's)
    exported under its ``exports/<assembly>/`` (or ``out``), four assemblies per task; the path
    of ``index.csv`` and the summaries."""
    run_dir = Path(source_run or run.run_dir)
    jobs = run_jobs(Path(run.workspace), run_dir, models, Path(out) if out else None,
                    answers=product())
    futures = [export_task.submit(b, limits) for b in batches(jobs, 4)]
    summaries = [s for f in futures for s in f.result()]
    return str(write_index(Path(out) if out else run_dir / "exports", summaries)), summaries


# ---------------------------------------------------------------- the inspection


INSPECT_VERSION = "inspect-1"


def inspect_config(options: InspectionOptions, tolerances: Tolerances) -> InspectConfig:
    """The inspection stage's config of the night's ``inspection`` options."""
    plan = DefectPlan(parts_per_variant=options.parts_per_defect, seed=options.seed) \
        if options.defects else DefectPlan(shifts_mm=(), turns_deg=(), missing=False)
    return InspectConfig(views=options.views, distance_m=options.distance_m,
                         near_m=options.near_m or None,
                         search_near_m=options.search_near_m or None, noise=options.noise,
                         defects=plan, search=options.search, tolerances=tolerances)


def _largest_first(mates: list[MatesSummary], catalog: pd.DataFrame) -> list[MatesSummary]:
    """The assemblies to inspect, the costliest first (its parts' box diagonals together: the
    points registration reads grow with their surfaces), so that two workers end together
    instead of one taking the largest last."""
    size = pd.Series([_diagonal(lo, hi) for lo, hi in zip(catalog["bbox_min"],
                                                          catalog["bbox_max"], strict=True)],
                     index=catalog.index, dtype=np.float64).groupby(catalog["source"]).sum()
    return sorted(mates, key=lambda m: -float(size.get(m.source, 0.0)))


def _diagonal(lo: Any, hi: Any) -> float:
    """A box's diagonal, mm; 0 for a part without one (a solid that failed to read)."""
    try:
        out = float(np.linalg.norm(np.asarray(hi, dtype=np.float64)
                                   - np.asarray(lo, dtype=np.float64)))
    except (TypeError, ValueError):
        return 0.0
    return out if np.isfinite(out) else 0.0


@task(name="inspect", **_CACHED)
def inspect_task(assembly: str, workspace: str, cfg: InspectConfig,
                 key: str) -> AssemblyInspection:
    """Capture one assembly and its planted variants as the inspection camera sees them, and
    check each against the design (in a worker process: two run on two cores)."""
    return inspect_isolated(assembly, Workspace(Path(workspace)), cfg, key)


@task(name="relate-inspection", **_CACHED)
def relate_inspection_task(folder: str, workspace: str, relations_models: str,
                           key: str) -> str:
    """The relations of an inspected assembly on the registered CAD (and the truth, on the
    same pair views), written beside its inspection rows; worked out in a worker process (two
    run on two cores)."""
    job = RelateInspectionJob(folder, workspace, relations_models)
    [outcome] = list(run_isolated(relate_inspection_job, [Job(folder, job)], ISOLATED))
    if outcome.result is None:
        raise RuntimeError(f"relations of the inspection {folder}: {outcome.error}")
    rows = outcome.result
    out = Path(folder) / "relations.parquet"
    with atomic_path(out) as tmp:
        pairs_frame(rows.to_dict("records")).to_parquet(tmp, index=False)
    return str(out)


@task(name="inspect-recording", **_CACHED)
def inspect_recording_task(assembly: str, recording: str, workspace: str, cfg: InspectConfig,
                           key: str) -> AssemblyInspection:
    """One recording made elsewhere checked against its assembly's design."""
    return inspect_recording_rows(assembly, Path(recording), Workspace(Path(workspace)), cfg,
                                  key)


def inspect_stage(mates: list[MatesSummary], run: Run, options: InspectionOptions,
                  tolerances: Tolerances, relations_models: str, recordings: str | None = None
                  ) -> tuple[list[AssemblyInspection], list[str]]:
    """Every assembly whose mates were extracted, inspected as built (one task each, keyed on
    its meshes, its mates, the config and the inspection's code), and its registered
    relations; then each recording of ``recordings`` in a folder named after one of them
    (``cadio.inspect.recording.assembly_recordings``) against it. The inspections and the
    relation files."""
    ws = Workspace(Path(run.workspace))
    cfg = inspect_config(options, tolerances)
    catalog = read_catalog(ws.catalog)
    futures = []
    for summary in _largest_first([m for m in mates if m.ok], catalog):
        parts = catalog[catalog["source"] == summary.source]["part_id"].astype(str)
        files = [ws.mesh(p) for p in sorted(parts)] + [Path(summary.path)]
        key = content_digest(files, cfg=cfg, epoch=run.epoch, version=INSPECT_VERSION,
                             code=inspection_digest())[:32]
        futures.append(inspect_task.submit(summary.assembly, run.workspace, cfg, key))
    done_ok = {m.assembly: m for m in mates if m.ok}
    for assembly, path in assembly_recordings(Path(recordings), set(done_ok)) if recordings \
            else []:
        parts = catalog[catalog["source"] == done_ok[assembly].source]["part_id"].astype(str)
        files = [ws.mesh(p) for p in sorted(parts)] + [Path(done_ok[assembly].path), path]
        key = content_digest(files, cfg=cfg, epoch=run.epoch, version=INSPECT_VERSION,
                             code=inspection_digest())[:32]
        futures.append(inspect_recording_task.submit(assembly, str(path), run.workspace, cfg,
                                                     key))
    related = []  # each assembly's relations start as soon as its inspection is done
    for future in as_completed(futures):
        done = future.result()
        if done.error or not cfg.search or not (Path(done.folder) / "found.parquet").is_file():
            continue
        key = content_digest([Path(done.folder) / "found.parquet", *_models(relations_models)],
                             version=INSPECT_VERSION, evidence=evidence_digest(),
                             methods=RELATION_METHODS.digest(), inputs=INPUTS.digest(),
                             reading=reading_digest())
        related.append(relate_inspection_task.submit(done.folder, run.workspace,
                                                     relations_models, key))
    return [f.result() for f in futures], sorted(f.result() for f in related)
