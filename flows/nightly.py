"""The nightly flow, the main job: ingest -> mates -> scenes -> captures -> completion ->
relations -> report.

Later stages (completion, relations, export) join this same flow. Each task is one call into
the packages; the flow only fans work out in coarse batches (SQLite-backed servers struggle
with thousands of tiny task runs) and logs one line per stage. Results are cached on content
hashes: a rerun over unchanged files does no CAD work again.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
from prefect import flow, get_run_logger, task
from prefect.artifacts import (
    create_link_artifact,
    create_markdown_artifact,
    create_table_artifact,
)
from prefect.states import Failed, State
from prefect.task_runners import ThreadPoolTaskRunner

from cadio.capture.coverage import ingested_parts
from cadio.capture.scan import ScanConfig
from cadio.catalog import read_catalog
from cadio.contracts import CaptureSummary, MatesSummary
from cadio.errors import DiskSpaceError, MachineError
from cadio.export.job import model_digests
from cadio.inspect.evaluate import AssemblyInspection
from cadio.inspect.recording import assembly_recordings
from cadio.truth.scene_config import night_scene_config
from cadio.truth.scenes import read_scenes
from cadio.workspace import Workspace, write_json
from cadio.workspace_claim import WorkspaceBusyError, claim_workspace
from flows.config import DEFAULT_NIGHT, ConfigError, NightConfig
from flows.preflight import check_night
from flows.settings import ingest_config, load_settings, runtime_settings
from flows.stale_runs import crash_dead_runs, label_flow_run
from flows.stopping import stop_on_signal
from flows.tasks import (
    Run,
    capture_stage,
    complete_stage,
    export_stage,
    generate_library_task,
    ingest_stage,
    inspect_stage,
    mates_stage,
    relate_stage,
    render_stage,
    scenes_task,
    start_run,
)
from models.evaluate import SHIPPED, Scores, write_completion_report
from models.relate import SHIPPED_RELATIONS, RelateBatch
from reports.asbuilt import verdicts, write_inspection_report
from reports.coverage import coverage_summary, read_part_coverage
from reports.relations import combine_pairs, write_relation_report
from reports.render import (
    IngestTotals,
    StageTotals,
    build_ingest_report,
    build_stage_report,
    write_ingest_report,
    write_stage_report,
)
from reports.run_report import RunReport, previous_runs, write_run_report
from reports.shapes import read_part_geometry
from reports.trends import DEFAULT_THRESHOLDS, read_thresholds


class ThresholdFailure(RuntimeError):
    """A night completed, but its report failed a per-category threshold or regressed."""

    def __init__(self, run_dir: str, failed: list[str]) -> None:
        self.run_dir, self.failed = run_dir, failed
        super().__init__(f"{len(failed)} threshold checks failed (report in {run_dir}): "
                         + "; ".join(failed[:5]) + (" ..." if len(failed) > 5 else ""))

    def __reduce__(self) -> tuple[type[ThresholdFailure], tuple[str, list[str]]]:
        return ThresholdFailure, (self.run_dir, self.failed)  # pickles with its fields


@dataclass(frozen=True)
class NightlySummary:
    """What a nightly run returns: where its reports are and the totals of each stage.

    coverage: per category (and ``all``) the library's parts (``parts_ingested``), those the
    completion stage scored (``parts_scored``) and their share (``coverage_parts``).
    verdict: the report's word (``reports.verdict.Verdict.word``): a night that checked
    nothing is ``UNCHECKED``, never ``PASS``.
    """

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
    run_report: str = ""
    failed_checks: list[str] = field(default_factory=list)
    stage_seconds: dict[str, float] = field(default_factory=dict)
    exports: str = ""
    export_status: dict[str, int] = field(default_factory=dict)
    coverage: dict[str, dict[str, Any]] = field(default_factory=dict)
    verdict: str = ""  # PASS, FAIL, or UNCHECKED: no threshold check applied
    as_built_report: str = ""  # inspect.md: each assembly as built against its design


@task(name="relations-report")
def relations_report_task(run: Run, batches: list[RelateBatch],
                          registered: Sequence[str] = ()) -> str:
    """The run's relation files (pairs, summary, near-boundary, assembly mates, Markdown);
    ``registered``: the inspection's relation files, whose ``registered`` rows join them."""
    failed = [f for b in batches for f in b.failed]
    notes = [f"{sum(b.pair_views for b in batches)} pair views of "
             f"{sum(b.captures for b in batches)} captures; {len(failed)} captures failed."]
    left_out = sum(b.left_out for b in batches)
    if left_out:  # a library of training parts would otherwise read as a night of no pairs
        notes.append(f"{left_out} pair views left out: a network trained on one of their parts "
                     "(their scores would not be held out).")
    notes += [f"- {f}" for f in failed]
    pairs = combine_pairs([Path(b.path) for b in batches])
    inspected = [pd.read_parquet(p) for p in registered if Path(p).is_file()]
    inspected = [f[f["input"] == "registered"] for f in inspected if not f.empty]
    if inspected:
        pairs = pd.concat([pairs, *inspected], ignore_index=True)
    joints = combine_pairs([Path(b.joints_path) for b in batches if b.joints_path], joints=True)
    return str(write_relation_report(Path(run.run_dir), pairs, notes, joints))


@task(name="as-built-report")
def as_built_report_task(run: Run, inspected: list[AssemblyInspection],
                         relations: list[str]) -> str:
    """The as-built files of the run (``as_built.csv``, the inspection's summaries) and its
    Prefect artifact: each assembly's verdict."""
    failed = [f"{i.assembly}: {i.error}" for i in inspected if i.error]
    path = write_inspection_report(Path(run.run_dir),
                                   [Path(i.folder) for i in inspected if not i.error],
                                   [Path(r) for r in relations], failed)
    as_built = Path(run.run_dir) / "as_built.parquet"
    if as_built.is_file():
        table = verdicts(pd.read_parquet(as_built))
        create_table_artifact(key="nightly-as-built", table=table.to_dict("records"),
                              description="Each assembly as built against its design "
                              "(as_built.csv holds every mate)")
    return str(path)


@task(name="completion-report")
def completion_report_task(run: Run, scores: list[Scores]) -> str:
    """The completion report of the run (``completion_parts.parquet``, categories, the
    coverage of the library's parts, the headline per distinct shape, Markdown)."""
    catalog = Workspace(Path(run.workspace)).catalog
    return str(write_completion_report(Path(run.run_dir), scores,
                                       ingested_parts(read_catalog(catalog)),
                                       read_part_geometry(catalog)))


@task(name="report")
def report_task(run: Run, catalog: str, mates: list[MatesSummary], scenes: str | None,
                captures: list[CaptureSummary]) -> tuple[IngestTotals, StageTotals]:
    """Write the run's reports and publish them as artifacts."""
    out = Path(run.run_dir)
    parts = read_catalog(Path(catalog))
    ingest = build_ingest_report(parts)
    write_ingest_report(out, ingest)
    categories = dict(zip(parts["part_id"].astype(str), parts["category"].astype(str),
                          strict=True))
    stages = build_stage_report(mates, read_scenes(Path(scenes)) if scenes else None, captures,
                                categories)
    write_stage_report(out, stages)
    create_markdown_artifact(key="nightly-ingest", markdown=ingest.markdown(),
                             description="Ingest report")
    create_markdown_artifact(key="nightly-stages", markdown=stages.markdown(),
                             description="Mates, scenes and captures per category")
    return ingest.totals, stages.totals


@task(name="run-report")
def run_report_task(run: Run, thresholds: str | None, history: int,
                    facts: dict[str, Any]) -> RunReport:
    """report.html, categories.csv (against thresholds and earlier runs), junit.xml,
    parts.parquet and pairs.parquet of the run."""
    ws = Workspace(Path(run.workspace))
    limits = read_thresholds(Path(thresholds) if thresholds else DEFAULT_THRESHOLDS)
    earlier = previous_runs(ws.root / "runs", run.run_id, history)
    return write_run_report(Path(run.run_dir), earlier, limits, ws.catalog, facts)


def publish(report: RunReport) -> None:
    """The run's Prefect artifacts: the threshold table, the report in Markdown, a link to
    report.html."""
    create_table_artifact(key="nightly-categories", table=report.table_rows(),
                          description="Per-category metrics against thresholds and the last run")
    create_markdown_artifact(key="nightly-report", markdown=report.markdown,
                             description="Nightly report")
    create_link_artifact(key="nightly-report-html", link=Path(report.html).resolve().as_uri(),
                         link_text="report.html", description="The full report (self-contained)")


class _Stopwatch:
    """Seconds of each stage, for its log line and the run's summary."""

    def __init__(self) -> None:
        self.last = time.perf_counter()
        self.seconds: dict[str, float] = {}

    def lap(self, stage: str) -> float:
        now = time.perf_counter()
        elapsed, self.last = now - self.last, now
        self.seconds[stage] = round(elapsed, 3)
        return elapsed


@flow(name="nightly", task_runner=ThreadPoolTaskRunner(max_workers=2))  # type: ignore[arg-type]
def nightly(config: NightConfig = DEFAULT_NIGHT) -> NightlySummary:
    """Ingest the library, extract assembly mates, generate scenes, capture them, complete the
    parts, relate the pairs, and report against the CAD, the paper and the previous nights.

    Args:
        config: everything the night runs with, grouped as library, capture, models,
            thresholds, runtime and tolerances (``flows.config.NightConfig``: every field
            with its description and allowed range).

    Returns:
        The run id, the paths of the report files, the totals and the seconds of each stage.

    Raises:
        ConfigError: the configuration names files that cannot be used, or a night that
            would check nothing (no file, no category, no model); raised before any work,
            or after the captures when not one of the recordings could be used.
        WorkspaceBusyError: another night holds the workspace (``cadio.workspace_claim``):
            refused at once, naming it.
        MachineError: the machine stopped the night (no space left, a workspace folder it
            cannot write, an I/O error); returned as a Failed state whose message names it,
            with nothing of it cached as a failed input.
        ThresholdFailure: a threshold failed (with ``fail_on_threshold``); the run's report
            and ``summary.json`` are complete, and the flow run ends Failed (a returned state
            whose data is the failure, so that no traceback is logged).
    """
    with stop_on_signal():
        log = get_run_logger()
        for warning in check_night(config):
            log.warning("%s", warning)
        label_flow_run()
        for name in crash_dead_runs():
            log.warning("flow run %r was left running by a night whose process is gone: "
                        "marked Crashed", name)
        try:
            with claim_workspace(Path(config.runtime.workspace), _holder(config)):
                state = _stages(config)
        except WorkspaceBusyError as busy:  # another night's workspace: named, no traceback
            return Failed(message=str(busy), data=busy)  # type: ignore[return-value]
        if not state.is_completed():  # the recordings named no part, or the machine failed
            failure = state.result(raise_on_failure=False)
            if isinstance(failure, (ConfigError, MachineError)):  # the reason, no traceback
                return Failed(message=state.message, data=failure)  # type: ignore[return-value]
        summary = state.result()
    if config.thresholds.fail_on_threshold and summary.failed_checks:
        # a returned Failed state, not a raised error: no crash's traceback on the console
        failure = ThresholdFailure(summary.run_dir, summary.failed_checks)
        return Failed(message=str(failure), data=failure)  # type: ignore[return-value]
    return summary


def _holder(config: NightConfig) -> dict[str, str]:
    """What the workspace's lock says of this night to another one."""
    from prefect.runtime import flow_run

    return {"what": "mateqa nightly", "flow_run": str(flow_run.name or ""),
            "library": config.library.path or "the built-in samples"}


def _stages(config: NightConfig) -> State[NightlySummary]:
    """The stages' subflow run, on the Dask cluster of the configuration or the
    environment when there is one."""
    address = config.runtime.dask_address
    address = load_settings().dask_address if address is None else address
    stages = run_stages if not address else run_stages.with_options(
        task_runner=_dask_runner(address))
    return stages(config, return_state=True)


def _dask_runner(address: str) -> Any:
    """Prefect's Dask task runner on an existing cluster."""
    from prefect_dask import DaskTaskRunner

    return DaskTaskRunner(address=address)


@flow(name="nightly-stages", task_runner=ThreadPoolTaskRunner(max_workers=2))  # type: ignore[arg-type]
def run_stages(config: NightConfig) -> NightlySummary:
    """Every stage of the nightly in order (one log line each): a subflow, so that its task
    runner can be a Dask cluster's while the code stays the same."""
    with stop_on_signal():
        label_flow_run()
        try:
            return stages_of(config)
        except ConfigError as err:  # an input's fault, answered by name (returned, not raised)
            return Failed(message=str(err), data=err)  # type: ignore[return-value]
        except (MachineError, OSError) as exc:  # the machine's: named, never a bad input
            fault = exc if isinstance(exc, MachineError) else MachineError.of(
                exc, exc.filename or config.runtime.workspace)
            if fault is None:
                raise
            return Failed(message=machine_failure(fault), data=fault)  # type: ignore[return-value]


def machine_failure(fault: MachineError) -> str:
    """What a night the machine stopped says: where, why, and that nothing was kept."""
    if isinstance(fault, DiskSpaceError):  # found before the stage started
        return (f"not enough free disk for the night: {fault}. Free space or give a workspace "
                "on a larger disk, then run the night again (the work finished before is "
                "reused)")
    return (f"the machine stopped the night, not an input: {fault}. No input was recorded as "
            "failed for it: free space or make the workspace writable, then run the night "
            "again (the work finished before is reused)")


def stages_of(config: NightConfig) -> NightlySummary:
    """The body of ``run_stages`` (``bench/speed/nightly.py`` runs it without Prefect)."""
    clock = _Stopwatch()
    run = start_run(config.runtime.workspace, config.tolerances)
    cad = _cad_stages(config, run, clock)
    captured = _capture_stages(config, run, cad, clock)
    learned = _learned_stages(config, run, captured, clock)
    inspected = _inspection_stage(config, run, cad, learned, clock)
    return _report_stages(config, run, cad, captured, learned, inspected, clock)


@dataclass(frozen=True)
class _Cad:
    """What the CAD stages left: the library, the catalog, the mates, the scenes, the limits."""

    library: str
    catalog: str
    mates: list[MatesSummary]
    scenes: Any
    limits: Any


def _cad_stages(config: NightConfig, run: Run, clock: _Stopwatch) -> _Cad:
    """Library, ingest, mates and scenes."""
    lib_cfg, tolerances, log = config.library, config.tolerances, get_run_logger()
    cfg = ingest_config(runtime_settings(config.runtime), lib_cfg.voxel_sizes, tolerances)
    lib = lib_cfg.path or generate_library_task(run.workspace)
    log.info("library: %s (%.1f s)", lib, clock.lap("library"))
    catalog = ingest_stage(lib, run, cfg, lib_cfg.batch_size, lib_cfg.categories)
    t = build_ingest_report(read_catalog(Path(catalog))).totals
    log.info("ingest: %d files (%d ok, %d failed, %d skipped), %d parts, %d reused (%.1f s)",
             t.files, t.ok, t.failed, t.skipped, t.parts, t.cached, clock.lap("ingest"))
    mates = mates_stage(catalog, run, tolerances, cfg.limits)
    log.info("mates: %d assemblies, %d failed, %d face mates (%.1f s)", len(mates),
             sum(not m.ok for m in mates), sum(m.face_mates for m in mates), clock.lap("mates"))
    cap = config.capture
    scenes = scenes_task(catalog, run.workspace,
                         night_scene_config(cap.seed, cap.pairs_per_relation, tolerances))
    log.info("scenes: %d from %d parts (%.1f s)", scenes.scenes, scenes.parts,
             clock.lap("scenes"))
    return _Cad(str(lib), catalog, mates, scenes, cfg.limits)


def _capture_stages(config: NightConfig, run: Run, cad: _Cad, clock: _Stopwatch
                    ) -> list[CaptureSummary]:
    """The scenes, the assemblies and every part captured, or the recordings read."""
    cap = config.capture
    scan_cfg = ScanConfig(views_per_scene=cap.views_per_scene, noise=cap.noise,
                          tolerances=config.tolerances)
    # recordings stand on their own; a rendered night captures the assemblies and every part
    captured = (capture_stage(cad.scenes, run, scan_cfg, cap.recordings) if cap.recordings
                else render_stage(cad.catalog, cad.scenes, cad.mates, run, scan_cfg))
    inspected = (assembly_recordings(Path(cap.recordings), {m.assembly for m in cad.mates
                                                            if m.ok})
                 if cap.recordings and config.inspection.enabled else [])
    if cap.recordings and all(c.error for c in captured) and not inspected:
        # each reason is in the report; an assembly's own recordings are the inspection's
        raise ConfigError([("capture.recordings", f"none of the {len(captured)} recording(s) "
                            "could be used, the night would check nothing: " + "; ".join(
                                f"{c.path}: {c.error}" for c in captured[:3]))])
    get_run_logger().info("captures: %d, %d failed, %d frames (%.1f s)", len(captured),
                          sum(bool(c.error) for c in captured),
                          sum(c.frames for c in captured), clock.lap("captures"))
    return captured


@dataclass(frozen=True)
class _Learned:
    """What the learned stages left: their checkpoints, reports, batches and coverage."""

    completion_dir: str
    relations_dir: str
    completion: str
    batches: list[RelateBatch]
    coverage: dict[str, dict[str, Any]]


def _learned_stages(config: NightConfig, run: Run, captured: list[CaptureSummary],
                    clock: _Stopwatch) -> _Learned:
    """Completion and relations of every captured part and pair."""
    log = get_run_logger()
    completion_dir = config.models.completion or str(SHIPPED)
    relations_dir = config.models.relations or str(SHIPPED_RELATIONS)
    scores = complete_stage(captured, run, completion_dir)
    completion = completion_report_task(run, scores)
    coverage = coverage_summary(read_part_coverage(Path(run.run_dir)))
    log.info("completion: %d scores of %d examples, %d failed, %d of %d parts scored "
             "(%.1f s)", sum(len(s.parts) for s in scores),
             sum(len(s.registration) for s in scores), sum(len(s.failed) for s in scores),
             coverage.get("all", {}).get("parts_scored", 0),
             coverage.get("all", {}).get("parts_ingested", 0), clock.lap("completion"))
    batches = relate_stage(captured, run, relations_dir, completion_dir)
    log.info("relations: %d pair views, %d rows, %d captures failed (%.1f s)",
             sum(b.pair_views for b in batches), sum(b.rows for b in batches),
             sum(len(b.failed) for b in batches), clock.lap("relations"))
    return _Learned(completion_dir, relations_dir, completion, batches, coverage)


def _inspection_stage(config: NightConfig, run: Run, cad: _Cad, learned: _Learned,
                      clock: _Stopwatch) -> tuple[list[AssemblyInspection], list[str]]:
    """Every assembly checked as built against its design (when the night asks for it)."""
    if not config.inspection.enabled:
        return [], []
    inspected, relations = inspect_stage(cad.mates, run, config.inspection, config.tolerances,
                                         learned.relations_dir, config.capture.recordings)
    get_run_logger().info(
        "inspection: %d assemblies, %d failed, %d captures, %d mates checked (%.1f s)",
        len(inspected), sum(bool(i.error) for i in inspected),
        sum(i.captures for i in inspected), sum(i.mates for i in inspected),
        clock.lap("inspection"))
    return inspected, relations


def _report_stages(config: NightConfig, run: Run, cad: _Cad, captured: list[CaptureSummary],
                   learned: _Learned, inspected: tuple[list[AssemblyInspection], list[str]],
                   clock: _Stopwatch) -> NightlySummary:
    """Every report, the verdict, the export, and ``summary.json`` last."""
    log, limits = get_run_logger(), config.thresholds
    relations = relations_report_task(run, learned.batches, inspected[1])
    as_built = as_built_report_task(run, inspected[0], inspected[1])
    ingest, stages = report_task(run, cad.catalog, cad.mates, cad.scenes.path, captured)
    facts = {"library": cad.library, "thresholds": limits.file or str(DEFAULT_THRESHOLDS),
             **{f"{k} seconds": v for k, v in clock.seconds.items()}}
    report = run_report_task(run, limits.file, limits.history, facts)
    publish(report)
    log.info("report: %s, %d threshold checks failed (%.1f s)", report.html,
             len(report.failed), clock.lap("report"))
    digests = model_digests({"relations": Path(learned.relations_dir),
                             "completion": Path(learned.completion_dir)})
    exports, exported = export_stage(run, digests, cad.limits)
    status = dict(Counter(e.status for e in exported))
    log.info("export: %d assemblies (%s) (%.1f s)", len(exported),
             ", ".join(f"{n} {k}" for k, n in sorted(status.items())) or "none",
             clock.lap("export"))
    summary = NightlySummary(
        run_id=run.run_id, library=cad.library, workspace=run.workspace, run_dir=run.run_dir,
        ingest_report=str(Path(run.run_dir) / "ingest.md"),
        stages_report=str(Path(run.run_dir) / "stages.md"),
        completion_report=learned.completion, relations_report=relations, ingest=ingest,
        stages=stages, run_report=str(report.html), failed_checks=list(report.failed),
        stage_seconds=clock.seconds, exports=exports, export_status=status,
        coverage=learned.coverage, verdict=report.verdict, as_built_report=as_built)
    write_json(Path(run.run_dir) / "summary.json", asdict(summary))
    Workspace(Path(run.workspace)).mark_latest(run.run_id)
    return summary
