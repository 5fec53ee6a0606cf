"""One recording checked against its design: ``mateqa inspect ASSEMBLY.step RECORDING.mcap``.

A recording as a driver writes it (colour, depth, camera info, perhaps tf; no scene, no masks,
no part names) of one assembly of the library: its STEP is read into a workspace (ingest and
mates, each file in a crash-isolated CAD worker), the recording's frames become one scan (the
support plane taken away), the whole assembly is found in it without any prior pose, then each
part is refined from its place in it (``routes.by_design``), and each CAD face mate is read as
built (``asbuilt``). A recording in which the design's parts explain too little of what the
camera saw shows something else, and is said to.
"""

from __future__ import annotations

import csv
import shutil
from collections.abc import Collection, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from cadio.errors import InputFileError
from cadio.inspect.asbuilt import (
    BROKEN,
    Limits,
    MateAsBuilt,
    PartAsBuilt,
    assembly_as_built,
    verdict,
)
from cadio.inspect.consensus import rest_in
from cadio.inspect.routes import RouteConfig, by_design, explained_share
from cadio.inspect.scan import scan_of
from cadio.inspect.stage import assembly_model
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.workspace import Workspace, atomic_path

# The columns of ``as_built.csv``: the mates stage's keys of a face mate, the status, why, and
# the residuals in the directions the mate constrains with their thresholds.
AS_BUILT_FIELDS = ("index_a", "index_b", "face_a", "face_b", "relation", "status", "reason",
                   "axis_distance_mm", "axis_distance_mm_threshold", "axis_angle_deg",
                   "axis_angle_deg_threshold", "plane_offset_mm", "plane_offset_mm_threshold",
                   "normal_angle_deg", "normal_angle_deg_threshold", "part_a", "part_b")
# The parts as placed must explain at least this share of the scan's points (the support
# taken away), or the recording shows something else than the assembly.
MIN_EXPLAINED = 0.4


class NotThisAssembly(InputFileError):
    """A recording in which the assembly's parts explain too little of what the camera saw."""


@dataclass(frozen=True)
class RecordingInspection:
    """One recording as built: the verdict, each CAD face mate, each part, and how much of
    the scan the placed parts explain."""

    assembly: str
    recording: str
    verdict: str
    mates: tuple[MateAsBuilt, ...]
    parts: dict[int, PartAsBuilt]
    part_ids: tuple[str, ...]
    explained: float
    frames: int
    warnings: tuple[str, ...] = field(default=())

    @property
    def broken(self) -> list[MateAsBuilt]:
        return [m for m in self.mates if m.status == BROKEN]

    def rows(self) -> list[dict[str, object]]:
        """The ``as_built.csv`` rows (``AS_BUILT_FIELDS``)."""
        out = []
        for m in self.mates:
            row: dict[str, object] = dict.fromkeys(AS_BUILT_FIELDS, "")
            row.update({k: v for k, v in m.row().items() if k in row})
            row["part_a"], row["part_b"] = self.part_ids[m.index_a], self.part_ids[m.index_b]
            out.append(row)
        return out


@dataclass(frozen=True)
class InspectRecordingConfig:
    """Knobs of a recording's inspection."""

    route: RouteConfig = field(default_factory=RouteConfig)
    tolerances: Tolerances = DEFAULT_TOLERANCES
    min_explained: float = MIN_EXPLAINED


def prepare_design(step: Path, ws: Workspace, tol: Tolerances = DEFAULT_TOLERANCES) -> str:
    """Read an assembly's STEP into the workspace (its parts, then its mates), each in a
    crash-isolated worker; the assembly's name.

    Raises:
        InputFileError: the file cannot be read, or holds fewer than two solids.
    """
    from cadio.cad.ingest import IngestConfig, ingest
    from cadio.catalog import read_catalog
    from cadio.truth.assemblies import assembly_jobs, extract_assembly_mates

    if not step.is_file():
        raise InputFileError(step, "no such file")
    library = ws.root / "design" / step.stem
    (library / "assembly").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(step, library / "assembly" / step.name)
    ingest(library, ws.root, IngestConfig(voxel_sizes=(32,), tolerances=tol))
    catalog = read_catalog(ws.catalog)
    mine = catalog[catalog["source"].map(lambda s: Path(str(s)).name) == step.name]
    failed = mine[mine["status"] != "ok"]
    if mine.empty or not failed.empty:
        why = str(failed["error"].iloc[0]) if not failed.empty else "not read"
        raise InputFileError(step, why)
    jobs = [j for j in assembly_jobs(catalog, ws.root, tol) if j.assembly == step.stem]
    if not jobs:
        raise InputFileError(step, f"holds {int(mine['n_solids'].max())} solid: an assembly "
                             "has two or more")
    (summary,) = extract_assembly_mates(jobs)
    if not summary.ok:
        raise InputFileError(step, summary.error)
    return step.stem


def inspect_recording(step: Path, recording: Path, ws: Workspace,
                      cfg: InspectRecordingConfig = InspectRecordingConfig()
                      ) -> RecordingInspection:
    """Check one recording of an assembly against its design (see the module docstring).

    Raises:
        InputFileError: the STEP or the recording cannot be read (``CaptureError`` for a
            recording), or the recording does not show the assembly (``NotThisAssembly``).
    """
    return check_recording(prepare_design(step, ws, cfg.tolerances), recording, ws, cfg)


def assembly_recordings(folder: Path, assemblies: Collection[str]) -> list[tuple[str, Path]]:
    """The recordings under ``folder`` that name their assembly: each ``*.mcap`` in a folder
    named after one of ``assemblies`` (its STEP file's name without ``.step``), with it."""
    return [(path.parent.name, path) for path in sorted(Path(folder).rglob("*.mcap"))
            if path.parent.name in assemblies]


def check_recording(assembly: str, recording: Path, ws: Workspace,
                    cfg: InspectRecordingConfig = InspectRecordingConfig()
                    ) -> RecordingInspection:
    """Check one recording against an assembly whose parts and mates the workspace holds.

    Raises:
        InputFileError: the recording cannot be read, or does not show the assembly.
    """
    from cadio.recordings.mcap_io import read_capture

    if not recording.is_file():
        raise InputFileError(recording, "not a regular file")
    frames = list(read_capture(recording))
    if not frames:
        raise InputFileError(recording, "no frame (no depth image with its camera info)")
    try:
        scan = scan_of(frames)
    except ValueError as exc:
        raise InputFileError(recording, str(exc)) from exc
    model = assembly_model(assembly, ws)
    mates = pd.read_parquet(ws.mates(assembly))
    try:
        nominal, parts, _ = by_design(model, scan, cfg.route)
    except ValueError as exc:
        raise InputFileError(recording, str(exc)) from exc
    found = [p for p in parts.values() if p.pose is not None]
    explained = explained_share(model, scan, parts, cfg.route)
    if explained < cfg.min_explained or not found:
        raise NotThisAssembly(recording, f"does not show {assembly}: its parts, placed as "
                              f"well as they fit, explain {explained:.0%} of the "
                              f"{len(scan.points)} points the camera saw (at least "
                              f"{cfg.min_explained:.0%} needed)")
    built = assembly_as_built(mates.to_dict("records"), parts, dict(enumerate(model.design)),
                              Limits.of(cfg.tolerances),
                              rest_in(model, parts, nominal, len(scan.cameras)))
    warnings = tuple(sorted({w for f in frames for w in f.meta.get("warnings", ())}))
    return RecordingInspection(assembly, str(recording), verdict(built), tuple(built), parts,
                               tuple(p.part_id for p in model.parts), explained, len(frames),
                               warnings)


def write_as_built(path: Path, result: RecordingInspection) -> Path:
    """``as_built.csv`` of one recording (``AS_BUILT_FIELDS``), written atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, tmp.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=AS_BUILT_FIELDS)
        writer.writeheader()
        for row in result.rows():
            writer.writerow({k: _cell(v) for k, v in row.items()})
    return path


def _cell(value: object) -> object:
    if isinstance(value, float):
        return "" if not np.isfinite(value) else f"{value:.4g}"
    return value


def summary_lines(result: RecordingInspection) -> list[str]:
    """The verdict in a few lines: the assembly, the verdict, each broken mate with its
    residuals, the parts that could not be inspected."""
    lines = [f"{result.assembly}: {result.verdict.upper()} ({len(result.mates)} mates, "
             f"{result.frames} frames, {result.explained:.0%} of the points explained)"]
    for m in result.broken:
        worst = [f"{r.name} {r.value:.2f} > {r.threshold:.2f}" for r in m.residuals
                 if r.broken] or [m.reason]
        lines.append(f"  broken: {m.relation} part {m.index_a} face {m.face_a} / part "
                     f"{m.index_b} face {m.face_b}: {'; '.join(worst)}")
    hidden = _problems(result.parts.values())
    if hidden:
        lines.append(f"  not inspected: {hidden}")
    counts = pd.Series([m.status for m in result.mates]).value_counts()
    lines.append("  " + ", ".join(f"{n} {s}" for s, n in counts.items()))
    return lines


def _problems(parts: Iterable[PartAsBuilt]) -> str:
    return ", ".join(f"part {p.index} ({p.problem})" for p in parts
                     if p.problem and p.problem != "missing")


def exit_code(result: RecordingInspection) -> int:
    """0 when every inspectable mate holds, 3 when one is broken."""
    return 3 if result.broken else 0

