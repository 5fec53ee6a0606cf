"""The export stage: per assembly of a run, the sidecar JSON, the XBF with notes and the
CadQuery script, each assembly in a crash-isolated worker.

``export_jobs`` makes one job per assembly of the catalog (every file with several solids,
whatever happened to it later), ``export_assemblies`` runs them and yields an
``ExportSummary`` per assembly. Nothing is dropped: an assembly whose export fails (its STEP
file changed or vanished, OpenCascade crashed) still gets a sidecar with status "failed" and
the reason, and ``index.csv`` lists every assembly with its status.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path

import pandas as pd

from cadio.cad.ingest import file_sha256
from cadio.catalog import read_catalog
from cadio.contracts import ExportSummary
from cadio.errors import ExportError
from cadio.export.notes import write_xbf
from cadio.export.predictions import (
    FAILED,
    NO_PREDICTIONS,
    PREDICTED,
    AssemblyMates,
    assembly_mates,
    mate_checks,
)
from cadio.export.script import mass_properties, write_script
from cadio.export.sidecar import write_sidecar
from cadio.sandbox import Job, Limits, run_isolated
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances, read_tolerances
from cadio.truth.mates import COLUMNS as MATES_COLUMNS
from cadio.workspace import Workspace, atomic_write

SCENE_PREFIX = "assembly-"


@dataclass(frozen=True)
class ExportJob:
    """One assembly to export.

    step: its STEP file; catalog: the run's ``catalog.parquet``; mates: its CAD mates table
    ("" when the mates stage failed for it); predictions: the run's ``relations_pairs``
    parquet ("" when there is none); out: the folder for its three files; answers: the
    (input, method) of the predictions it exports (the product's, ``reports.methods.product``).
    """

    assembly: str
    category: str
    step: str
    sha256: str
    catalog: str
    mates: str
    predictions: str
    out: str
    run_id: str
    timestamp: str
    answers: tuple[str, str]
    models: Mapping[str, str] = field(default_factory=dict)
    tolerances: Tolerances = DEFAULT_TOLERANCES
    reason: str = ""
    captured: bool = True
    as_built: str = ""  # the run's as_built.parquet ("" when the run inspected nothing)


def file_names(assembly: str) -> dict[str, str]:
    """The three files of an assembly's export folder."""
    return {"sidecar": f"{assembly}.mates.json", "xbf": f"{assembly}.xbf",
            "script": f"{assembly}_assembly.py"}


@dataclass(frozen=True)
class RunFiles:
    """What the export jobs of one run share: its catalog, the mates folder, its predictions
    (None: none), the exports folder, its id and time, its models, tolerances and answers."""

    catalog: Path
    mates: Path
    predictions: Path | None
    out: Path
    run_id: str
    timestamp: str
    models: Mapping[str, str]
    tolerances: Tolerances
    answers: tuple[str, str]
    as_built: Path | None = None


def export_jobs(catalog: pd.DataFrame, run: RunFiles) -> list[ExportJob]:
    """A job per assembly (catalog file with several ok solids), by source path."""
    ok = catalog[(catalog["status"] == "ok") & (catalog["n_solids"] > 1)]
    jobs = []
    for source, rows in ok.groupby("source", sort=True):
        name = Path(str(source)).stem
        mates = run.mates / f"{name}.parquet"
        capture = run.mates.parent / "captures" / f"{SCENE_PREFIX}{name}.mcap"
        predictions = run.predictions
        jobs.append(ExportJob(
            assembly=name, category=str(rows["category"].iloc[0]), step=str(source),
            sha256=str(rows["source_sha256"].iloc[0]), catalog=str(run.catalog),
            mates=str(mates) if mates.is_file() else "",
            predictions=str(predictions) if predictions and predictions.is_file() else "",
            out=str(run.out / name), run_id=run.run_id, timestamp=run.timestamp,
            answers=run.answers, models=dict(run.models), tolerances=run.tolerances,
            reason="" if mates.is_file() else "no CAD mates (the mates stage failed for it)",
            captured=capture.is_file(),
            as_built=str(run.as_built) if run.as_built and run.as_built.is_file() else ""))
    return jobs


def run_jobs(workspace: Path, run_dir: Path, models: Mapping[str, str],
             out: Path | None = None, *, answers: tuple[str, str]) -> list[ExportJob]:
    """The export jobs of one finished run of a workspace: its catalog and mates, the run's
    ``relations_pairs.parquet`` and ``tolerances.json``; files under ``<run>/exports/`` (or
    ``out``); the predictions of ``answers`` (input, method).

    Raises:
        ExportError: the workspace has no catalog or the run folder does not exist.
    """
    ws = Workspace(Path(workspace))
    run_dir = Path(run_dir).resolve()
    if not ws.catalog.is_file():
        raise ExportError(ws.catalog, "no catalog: the workspace was never ingested")
    if not run_dir.is_dir():
        raise ExportError(run_dir, "no such run folder")
    tol_file = run_dir / "tolerances.json"
    tol = read_tolerances(tol_file) if tol_file.is_file() else DEFAULT_TOLERANCES
    run_id = run_dir.name
    try:
        stamp = datetime.strptime(run_id, "%Y%m%dT%H%M%S%fZ").replace(tzinfo=UTC).isoformat()
    except ValueError:  # a run folder named by hand: its time of last change
        stamp = datetime.fromtimestamp(run_dir.stat().st_mtime, UTC).isoformat()
    return export_jobs(read_catalog(ws.catalog), RunFiles(
        ws.catalog, ws.root / "mates", run_dir / "relations_pairs.parquet",
        out or run_dir / "exports", run_id, stamp, models, tol, answers,
        run_dir / "as_built.parquet"))


def model_digests(folders: Mapping[str, Path]) -> dict[str, str]:
    """Checkpoint name -> the first 16 hex of its content hash, for every ``*.pt`` of the
    named model folders ({"relations/ltn_completed.pt": "3f2a..."})."""
    return {f"{kind}/{p.name}": file_sha256(p)[:16] for kind, folder in folders.items()
            for p in sorted(Path(folder).glob("*.pt"))}


def _predictions(job: ExportJob) -> pd.DataFrame:
    if not job.predictions:
        return pd.DataFrame(columns=["scene", "view", "part_a", "part_b", "relation", "truth",
                                     "predicted", "confidence"])
    inp, method = job.answers
    return pd.read_parquet(job.predictions, filters=[
        ("scene", "==", f"{SCENE_PREFIX}{job.assembly}"), ("input", "==", inp),
        ("method", "==", method)])


def read_inputs(job: ExportJob) -> AssemblyMates:
    """The assembly's export record from the run's files.

    Raises:
        ExportError: the catalog has no ok solid of the assembly.
    """
    catalog = pd.read_parquet(job.catalog)
    rows = catalog[(catalog["source"] == job.step) & (catalog["status"] == "ok")]
    if rows.empty:
        raise ExportError(job.step, "the run's catalog has no readable solid of this assembly")
    mates = (pd.read_parquet(job.mates) if job.mates else
             pd.DataFrame(columns=list(MATES_COLUMNS)))
    record = assembly_mates(job.assembly, job.category, job.step, job.sha256, rows, mates,
                            _predictions(job), run_id=job.run_id, models=dict(job.models),
                            tolerances=job.tolerances.as_dict(), reason=job.reason)
    if job.as_built:
        rows = pd.read_parquet(job.as_built, filters=[("assembly", "==", job.assembly)])
        record = replace(record, as_built=mate_checks(latest_capture(rows)))
    if record.status == NO_PREDICTIONS and not job.reason:
        why = ("the run has no relation predictions" if not job.predictions else
               "the assembly was not captured (see the run's stages report)"
               if not job.captured else
               "captured, but no view shows both parts of a labelled pair well enough to "
               "relate them (occluded or too few points)")
        record = replace(record, reason=why)
    return record


def export_assembly(job: ExportJob) -> ExportSummary:
    """Write the three files of one assembly (the job of an isolated worker).

    Raises:
        InputFileError: the STEP file is unreadable or changed since the run, or a file
            cannot be written (``ExportError``).
    """
    start = time.perf_counter()
    mates = read_inputs(job)
    out = Path(job.out)
    names = file_names(job.assembly)
    step = Path(job.step)
    try:
        out.mkdir(parents=True, exist_ok=True)
        notes, solids = write_xbf(step, mates, out / names["xbf"], job.timestamp)
        write_script(out / names["script"], mates, step, mass_properties(solids),
                     job.tolerances.contact_mm, job.tolerances.mate_angle_deg)
        write_sidecar(out / names["sidecar"], mates)
    except OSError as exc:
        raise ExportError(out, f"could not write the export ({exc})") from exc
    agreement = mates.agreement()
    return ExportSummary(
        assembly=job.assembly, category=job.category, status=mates.status, reason=mates.reason,
        sidecar=str(out / names["sidecar"]), xbf=str(out / names["xbf"]),
        script=str(out / names["script"]), notes=notes, pairs=len(mates.pairs),
        predicted_pairs=sum(p.status == PREDICTED for p in mates.pairs),
        constraints=sum(len(p.constraints()) for p in mates.pairs),
        relation_accuracy=_nan(agreement["relation_accuracy"]),
        joint_agreement=_nan(agreement["joint_agreement"]),
        seconds=time.perf_counter() - start)


def latest_capture(rows: pd.DataFrame) -> pd.DataFrame:
    """An assembly's as-built rows of one capture: the last of its recordings made elsewhere
    (by name) where the night read any, else its own inspection capture."""
    if "capture" not in rows or rows.empty:
        return rows
    captures = sorted(set(rows["capture"].astype(str)))
    recorded = [c for c in captures if not c.startswith("inspect-")]
    chosen = (recorded or captures)[-1]
    return rows[rows["capture"].astype(str) == chosen]


def _nan(value: float | None) -> float:
    return float("nan") if value is None else float(value)


def failed_export(job: ExportJob, reason: str, seconds: float = 0.0) -> ExportSummary:
    """The summary of an assembly whose export failed, after writing its sidecar with status
    "failed" and the reason (so the assembly is never silently missing)."""
    out = Path(job.out)
    path = out / file_names(job.assembly)["sidecar"]
    record = AssemblyMates(assembly=job.assembly, category=job.category, source=job.step,
                           source_sha256=job.sha256, status=FAILED, parts=(), pairs=(),
                           reason=reason, run_id=job.run_id, models=dict(job.models),
                           tolerances=job.tolerances.as_dict())
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_sidecar(path, record)
    except OSError:
        return ExportSummary(assembly=job.assembly, category=job.category, status=FAILED,
                             reason=reason, seconds=seconds)
    return ExportSummary(assembly=job.assembly, category=job.category, status=FAILED,
                         reason=reason, sidecar=str(path), seconds=seconds)


def export_assemblies(jobs: Sequence[ExportJob],
                      limits: Limits | None = None) -> Iterator[ExportSummary]:
    """Export every job's assembly, each in an isolated worker; a summary per assembly (a
    failure, bad input or crash, gives a failed summary and sidecar; the others go on)."""
    for outcome in run_isolated(export_assembly, [Job(j.step, j) for j in jobs],
                                limits or Limits()):
        if outcome.result is not None:
            yield outcome.result
            continue
        reason = outcome.error.reason if outcome.error is not None else "no result"
        yield failed_export(outcome.job.payload, reason, outcome.seconds)


INDEX_COLUMNS = tuple(ExportSummary.__dataclass_fields__)


def write_index(folder: Path, summaries: Sequence[ExportSummary]) -> Path:
    """``index.csv`` of an export folder: one row per assembly (``ExportSummary`` fields)."""
    frame = pd.DataFrame([s.to_dict() for s in sorted(summaries, key=lambda s: s.assembly)],
                         columns=list(INDEX_COLUMNS))
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "index.csv"
    with atomic_write(path, "w") as fh:
        frame.to_csv(fh, index=False)
    return path
