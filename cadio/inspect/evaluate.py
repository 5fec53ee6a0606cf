"""One assembly inspected as built, every planted variant of it, and the rows its scores read.

``inspect_assembly`` captures the intact assembly and its variants (``stage.capture_variant``),
inspects each as a recording (``stage.inspect_capture``), and turns what it found into rows:
each CAD mate as built, by the product (``registered``: the design route's poses) and by the
``design`` baseline (every part where the aligned design puts it, which must catch nothing);
each part's pose error against where it stood, least over its symmetries; whether each planted
defect was caught; whether each part of each capture was flagged. The search route's poses of
the intact capture (found without the design) are kept for the ``registered`` relations. The
rows are written under ``inspect/<key>/`` of the workspace; the run's tables are made from them
(``reports.asbuilt``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cadio.inspect.asbuilt import BROKEN, MateAsBuilt
from cadio.inspect.defects import MISSING, Variant
from cadio.inspect.stage import (
    ALL_VIEWS,
    InspectConfig,
    Inspected,
    assembly_model,
    capture_variant,
    inspect_capture,
    pose_rows,
    read_truth,
    scored_as,
    shares,
    variants_of,
)
from cadio.sandbox import Job, Limits, run_isolated
from cadio.workspace import Workspace, atomic_path

log = logging.getLogger(__name__)

REGISTERED, DESIGN = "registered", "design"  # the product's method, and its baseline
TABLES = ("mates", "poses", "defects", "parts", "found", "shares")


@dataclass(frozen=True)
class AssemblyInspection:
    """Where one assembly's inspection rows are (``inspect/<key>/<table>.parquet``), how many
    captures and mates it holds, the wall time per phase, and why it failed ("" if it did
    not)."""

    assembly: str
    folder: str
    captures: int = 0
    mates: int = 0
    seconds: dict[str, float] = field(default_factory=dict)
    error: str = ""


def inspect_assembly(assembly: str, ws: Workspace, cfg: InspectConfig, key: str
                     ) -> AssemblyInspection:
    """Capture and inspect one assembly and its variants; its rows under ``inspect/<key>/``.
    A failure comes back as the record's error (the night goes on)."""
    folder = ws.root / "inspect" / key
    clock: dict[str, float] = {"capture": 0.0, "inspect": 0.0, "score": 0.0}
    try:
        mates = pd.read_parquet(ws.mates(assembly))
        model = assembly_model(assembly, ws)
        tables: dict[str, list[dict[str, Any]]] = {t: [] for t in TABLES}
        variants = variants_of(model, mates, cfg)
        for variant in variants:
            start = time.perf_counter()
            path = capture_variant(model, variant, ws, cfg)
            clock["capture"] += time.perf_counter() - start
            start = time.perf_counter()
            found = inspect_capture(model, path, mates, cfg, search=cfg.search and
                                    variant.name == "intact", fixture=np.eye(4))
            clock["inspect"] += time.perf_counter() - start
            start = time.perf_counter()
            score_capture(model, variant, path, found, ws, tables)
            if variant.name == "intact":
                folder.mkdir(parents=True, exist_ok=True)
                _deviation(model, path, found[0], folder / f"deviation-{assembly}.npz", cfg)
            clock["score"] += time.perf_counter() - start
        folder.mkdir(parents=True, exist_ok=True)
        for name, rows in tables.items():
            with atomic_path(folder / f"{name}.parquet") as tmp:
                pd.DataFrame(rows).to_parquet(tmp, index=False)
        return AssemblyInspection(assembly, str(folder), len(variants),
                                  len(tables["mates"]), clock)
    except (OSError, ValueError, KeyError) as exc:
        log.warning("inspection of %s: %s", assembly, exc)
        return AssemblyInspection(assembly, str(folder), seconds=clock,
                                  error=f"{type(exc).__name__}: {exc}")


@dataclass(frozen=True)
class InspectJob:
    """One assembly's inspection, as a worker process runs it (``inspect_isolated``)."""

    assembly: str
    workspace: str
    cfg: InspectConfig
    key: str


def inspect_job(job: InspectJob) -> AssemblyInspection:
    return inspect_assembly(job.assembly, Workspace(Path(job.workspace)), job.cfg, job.key)


# An inspection is minutes of numpy, k-d trees and ray casts: in a worker process of its own,
# two of them run on two cores (threads share one interpreter's lock: two assemblies in the
# night's threads took 1.2x the time of one), each on one thread of its libraries' (two
# quadcopter inspections side by side: 38.7 s with their threads, 29.5 s with one each); a
# crash in open3d takes the worker, not the night.
ISOLATED = Limits(seconds=3600.0, memory_mb=16384, workers=1, threads=1)


def inspect_isolated(assembly: str, ws: Workspace, cfg: InspectConfig, key: str,
                     limits: Limits = ISOLATED) -> AssemblyInspection:
    """``inspect_assembly`` in a worker process (``cadio.sandbox``); a worker that dies or
    runs out of time comes back as the record's error."""
    job = InspectJob(assembly, str(ws.root), cfg, key)
    for outcome in run_isolated(inspect_job, [Job(assembly, job)], limits):
        if outcome.result is not None:
            return outcome.result
        log.warning("inspection of %s: %s", assembly, outcome.error)
        return AssemblyInspection(assembly, str(ws.root / "inspect" / key),
                                  error=str(outcome.error))
    raise AssertionError("run_isolated yields one outcome per job")


RECORDING = "recording"  # the variant of a recording made elsewhere (no truth to score)


def inspect_recording_rows(assembly: str, recording: Path, ws: Workspace, cfg: InspectConfig,
                           key: str) -> AssemblyInspection:
    """One recording of an assembly (made elsewhere: no masks, no truth) checked against its
    design; its mates as built under ``inspect/<key>/mates.parquet``, as the product's rows
    of variant ``recording``. A recording that cannot be read or does not show the assembly
    comes back as the record's error (the night goes on)."""
    from cadio.errors import InputFileError
    from cadio.inspect.recording import InspectRecordingConfig, check_recording

    folder = ws.root / "inspect" / key
    start = time.perf_counter()
    try:
        result = check_recording(assembly, recording, ws,
                                 InspectRecordingConfig(cfg.route, cfg.tolerances))
    except (InputFileError, OSError, ValueError) as exc:
        log.warning("inspection of %s: %s", recording, exc)
        return AssemblyInspection(assembly, str(folder), seconds={
            "inspect": time.perf_counter() - start}, error=str(exc))
    base = {"assembly": assembly, "variant": RECORDING,
            "capture": f"{recording.parent.name}/{recording.name}", "views": ALL_VIEWS,
            "method": REGISTERED}
    rows = [{**base, **m.row(), "part_a": result.part_ids[m.index_a],
             "part_b": result.part_ids[m.index_b]} for m in result.mates]
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / "mates.parquet") as tmp:
        pd.DataFrame(rows).to_parquet(tmp, index=False)
    return AssemblyInspection(assembly, str(folder), 1, len(rows),
                              {"inspect": time.perf_counter() - start})


def score_capture(model: Any, variant: Variant, path: Path, found: Sequence[Inspected],
                  ws: Workspace, tables: dict[str, list[dict[str, Any]]]) -> None:
    """The rows of one capture's inspections (each set of views)."""
    truth = read_truth(ws, path.stem)
    for inspected in found:
        seen = shares(model, path, truth, None if inspected.views == ALL_VIEWS else
                      [int(inspected.views)])
        base = {"assembly": model.name, "variant": variant.name, "capture": path.stem,
                "views": inspected.views}
        names = {i: p.part_id for i, p in enumerate(model.parts)}
        for method, mates in ((REGISTERED, inspected.mates), (DESIGN, inspected.baseline)):
            tables["mates"] += [{**base, "method": method, **m.row(),
                                 "part_a": names[m.index_a], "part_b": names[m.index_b]}
                                for m in mates]
            tables["defects"] += _defect_rows(base, method, variant, mates, inspected)
            tables["parts"] += _part_rows(base, method, variant, mates, inspected,
                                          len(model.parts))
        for row in pose_rows(model, inspected, truth):
            tables["poses"].append({**base, **row, "visible_share": seen.get(row["index"],
                                                                              np.nan)})
        tables["shares"] += [{**base, "index": i, "part_id": names[i], "visible_share": v}
                             for i, v in sorted(seen.items())]
        scored = scored_as(model, inspected.found, truth)
        tables["found"] += [{**base, "index": f.index, "part_id": names[f.index],
                             "segment": f.segment, "fitness": f.fit.fitness,
                             "coverage": f.fit.coverage, "rmse_mm": f.fit.rmse_mm,
                             "sigma_mm": f.sigma_mm, "sigma_deg": f.sigma_deg,
                             "pose": f.fit.pose.ravel().tolist(),
                             "scored_index": scored.get(f.segment, (-1, None))[0],
                             "scored_pose": _ravel(scored.get(f.segment, (-1, None))[1])}
                            for f in inspected.found]


def _ravel(pose: Any) -> list[float] | None:
    return None if pose is None else [float(x) for x in np.asarray(pose).ravel()]


def _deviation(model: Any, path: Path, inspected: Inspected, out: Path,
               cfg: InspectConfig) -> None:
    """The first view's scan-to-CAD deviation image of the intact capture, at the registered
    poses (the design route), with the share within the deviation tolerance."""
    from cadio.inspect.deviation import deviation_image, within
    from cadio.recordings.mcap_io import read_capture

    frame = next(iter(read_capture(path)))
    poses = {i: p.pose for i, p in inspected.parts.items() if p.pose is not None}
    image = deviation_image(model.parts, poses, frame)
    with atomic_path(out) as tmp:
        np.savez_compressed(tmp, deviation_mm=image, tolerance_mm=cfg.deviation_mm,
                            within=within(image, cfg.deviation_mm))


def flagged(mates: Sequence[MateAsBuilt], inspected: Inspected, method: str) -> set[int]:
    """The parts a method flags: a part of a broken mate, or (the product only) missing."""
    out = {i for m in mates if m.status == BROKEN for i in (m.index_a, m.index_b)}
    if method == REGISTERED:
        out |= {i for i, p in inspected.parts.items() if p.problem == "missing"}
    return out


def _defect_rows(base: dict[str, Any], method: str, variant: Variant,
                 mates: Sequence[MateAsBuilt], inspected: Inspected) -> list[dict[str, Any]]:
    """Per planted defect: caught (its part flagged: a mate of it broken, or it missing)."""
    hit = flagged(mates, inspected, method)
    return [{**base, "method": method, "index": d.index, "kind": d.kind, "size": d.size,
             "caught": d.index in hit,
             "inspectable": inspected.parts[d.index].problem in ("", "missing")
             if d.kind != MISSING else True} for d in variant.defects]


def _part_rows(base: dict[str, Any], method: str, variant: Variant,
               mates: Sequence[MateAsBuilt], inspected: Inspected, n: int
               ) -> list[dict[str, Any]]:
    """Per part of the capture: defective or not, flagged or not, inspectable or not (the
    false alarms are the flagged parts of no defect and no mate with a defective part)."""
    hit = flagged(mates, inspected, method)
    bad = {d.index for d in variant.defects}
    near_bad = {i for m in mates if {m.index_a, m.index_b} & bad for i in (m.index_a, m.index_b)}
    return [{**base, "method": method, "index": i, "defective": i in bad,
             "beside_defect": i in near_bad and i not in bad, "flagged": i in hit,
             "inspectable": inspected.parts.get(i) is not None
             and inspected.parts[i].problem in ("", "missing")} for i in range(n)]


def inspection_digest() -> str:
    """SHA-256 of the inspection's code (every module of ``cadio.inspect``): its cached rows
    are redone when the code that made them changes."""
    import hashlib

    digest = hashlib.sha256()
    for source in sorted(Path(__file__).parent.glob("*.py")):
        digest.update(source.name.encode() + source.read_bytes())
    return digest.hexdigest()


def read_tables(folder: Path) -> dict[str, pd.DataFrame]:
    """One assembly's inspection rows (an empty frame for a table it lacks)."""
    return {name: pd.read_parquet(folder / f"{name}.parquet")
            if (folder / f"{name}.parquet").is_file() else pd.DataFrame() for name in TABLES}
