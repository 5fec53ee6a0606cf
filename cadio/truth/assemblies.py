"""The mates stage over a library: one crash-isolated worker job per assembly file.

The catalog says which files are assemblies (several solids read ok) and which part id each
solid has; ``assembly_jobs`` turns that into typed jobs, ``extract_assembly_mates`` runs
``mates_job`` on each in an isolated worker (OpenCascade may hang or crash on a bad file:
that file becomes a failed ``MatesSummary`` and the others go on) and yields one summary per
assembly. Each job writes ``mates/<assembly>.parquet`` with the tolerances it used.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from cadio.contracts import MatesSummary
from cadio.sandbox import Job, Limits, run_isolated
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.mates import read_assembly_mates, write_mates
from cadio.workspace import Workspace

# Bump when the mates change meaning (definitions, tolerances' use), so cached results of
# earlier runs are recomputed. 2: concentric face mates within 1 mm, fit/clearance, fuzzy
# coincident overlaps, sampled fits of freeform faces. 3: part-level concentric and coincident
# are the face mates, parallel and perpendicular use the dominant plane directions, and the
# answers near a tolerance are in the metadata.
MATES_VERSION = "3"


@dataclass(frozen=True)
class AssemblyJob:
    """One assembly file for the mates stage.

    part_ids: solid index -> catalog part id. workspace: where ``mates/`` goes.
    """

    path: str
    assembly: str
    category: str
    workspace: str
    part_ids: dict[int, str]
    tolerances: Tolerances = DEFAULT_TOLERANCES


def assembly_jobs(catalog: pd.DataFrame, workspace: Path,
                  tol: Tolerances = DEFAULT_TOLERANCES) -> list[AssemblyJob]:
    """A job per catalog file with several ok solids, by source path."""
    ok = catalog[(catalog["status"] == "ok") & (catalog["n_solids"] > 1)]
    jobs = []
    for source, rows in ok.groupby("source", sort=True):
        jobs.append(AssemblyJob(
            path=str(source), assembly=Path(str(source)).stem,
            category=str(rows["category"].iloc[0]), workspace=str(workspace),
            part_ids={int(i): str(p) for i, p in zip(rows["solid_index"], rows["part_id"],
                                                     strict=True)},
            tolerances=tol))
    return jobs


def mates_job(job: AssemblyJob) -> MatesSummary:
    """Extract and write one assembly's mates (the job of an isolated worker).

    Raises:
        StepReadError: the file cannot be read.
    """
    result = read_assembly_mates(Path(job.path), job.tolerances, part_ids=job.part_ids)
    out = Workspace(Path(job.workspace)).mates(job.assembly)
    write_mates(out, result.table)
    joints = result.level("joint")
    return MatesSummary(
        assembly=job.assembly, category=job.category, source=job.path, status="ok",
        path=str(out), n_parts=result.n_parts, n_pairs=result.n_pairs,
        n_box_pairs=result.n_box_pairs, n_contact_pairs=result.n_contact_pairs,
        face_mates=len(result.level("face")), relations=len(result.level("part")),
        joints=len(joints),
        joint_types={str(k): int(v) for k, v in joints["relation"].value_counts().items()},
        phase_seconds=dict(result.seconds))


def extract_assembly_mates(jobs: Sequence[AssemblyJob],
                           limits: Limits | None = None) -> Iterator[MatesSummary]:
    """Mates of every job's assembly, each in an isolated worker; a summary per assembly.

    A file that fails (bad input, time-out, crash, memory) gives a failed summary with the
    reason; the others are unaffected.
    """
    for outcome in run_isolated(mates_job, [Job(j.path, j) for j in jobs], limits or Limits()):
        job = outcome.job.payload
        if outcome.result is not None:
            yield MatesSummary(**{**outcome.result.to_dict(), "seconds": outcome.seconds})
            continue
        reason = outcome.error.reason if outcome.error is not None else "no result"
        yield MatesSummary(assembly=job.assembly, category=job.category, source=job.path,
                           status="failed", error=reason, seconds=outcome.seconds)
