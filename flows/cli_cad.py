"""The commands of ``mateqa`` that read CAD without Prefect: ``ingest``, ``mates``,
``capture``, ``export`` and ``samples``."""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from cadio.errors import InputFileError

if TYPE_CHECKING:
    from cadio.capture.scan import ScanConfig
    from cadio.contracts import CaptureSummary
    from cadio.sandbox import Limits


@contextmanager
def progress(description: str, total: int | None) -> Iterator[Callable[[str], None]]:
    """A progress bar on stderr (a counter when ``total`` is None); yields the function that
    advances it by one item."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    columns = (*Progress.get_default_columns()[:1], BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn())
    with Progress(*columns, transient=True) as bar:
        task = bar.add_task(description, total=total)
        yield lambda item: bar.advance(task)



def cmd_ingest(args: argparse.Namespace) -> int:
    from cadio.cad.ingest import discover, ingest
    from cadio.errors import MachineError
    from cadio.workspace_claim import WorkspaceBusyError, claim_workspace
    from flows.settings import ingest_config, runtime_settings
    from reports.render import build_ingest_report

    config = args.config
    library, workspace = Path(config.library.path), Path(config.runtime.workspace)
    # in the command's own process the workers are the command's: 0 means one per core
    cfg = ingest_config(runtime_settings(config.runtime), config.library.voxel_sizes,
                        config.tolerances, default_workers=os.cpu_count() or 1)
    try:
        categories = config.library.categories
        found = [f for f in discover(library) if not categories or f.category in categories]
        with claim_workspace(workspace, {"what": "mateqa ingest"}), \
                progress("ingest", len(found)) as advance:
            catalog = ingest(library, workspace, cfg, on_file=advance,
                             categories=categories)
    except (InputFileError, WorkspaceBusyError) as exc:
        print(f"mateqa ingest: {exc}", file=sys.stderr)
        return 2
    except MachineError as exc:
        print(f"mateqa ingest: the machine stopped the ingest, not a file: {exc}",
              file=sys.stderr)
        return 1
    print(build_ingest_report(catalog).markdown())
    print(f"catalog: {workspace / 'catalog.parquet'}")
    return 0


def cmd_mates(args: argparse.Namespace) -> int:
    from cadio.truth.assemblies import AssemblyJob, extract_assembly_mates
    from cadio.truth.mates import read_mates

    job = AssemblyJob(path=str(args.step), assembly=args.step.stem, category="",
                      workspace=str(args.workspace), part_ids={}, tolerances=args.tolerances)
    with progress("mates", None):  # in a CAD worker, as ingest reads: a crash is an error
        (summary,) = extract_assembly_mates([job], _limits())
    if not summary.ok:
        print(f"mateqa mates: {args.step}: {summary.error}", file=sys.stderr)
        return 2
    print(f"{summary.n_parts} parts, {summary.n_pairs} pairs, {summary.n_contact_pairs} in "
          "contact")
    table = read_mates(Path(summary.path))
    if table.empty:
        print("no mates or relations: one part has no pair" if summary.n_parts < 2 else
              "no mates or relations between its parts")
    else:
        print(table.groupby(["level", "relation"]).size().to_string())
    print(f"mates: {summary.path}")
    return 0


def cmd_capture(args: argparse.Namespace) -> int:
    from cadio.capture.scan import ScanConfig
    from cadio.recordings.mcap_io import summarise_capture
    from cadio.sandbox import Job, run_isolated

    if args.read is not None:
        read = summarise_capture(args.read)
        print(json.dumps(read.to_dict(), indent=1))
        return 2 if read.error else 0
    if args.target is None:
        print("mateqa capture: give STEP_OR_SCENE, or --read MCAP", file=sys.stderr)
        return 2
    cfg = ScanConfig(views_per_scene=args.views, noise=args.noise, tolerances=args.tolerances)
    job = Job(str(args.target), (str(args.target), str(args.workspace), cfg))
    with progress(f"capture, {args.views} views", None):
        (outcome,) = run_isolated(capture_job, [job], _limits())
    if outcome.error is not None or outcome.result is None:
        print(f"mateqa capture: {outcome.error}", file=sys.stderr)
        return 2
    print(json.dumps(outcome.result.to_dict(), indent=1))
    return 0


def capture_job(payload: tuple[str, str, ScanConfig]) -> CaptureSummary:
    """``capture_step`` in a CAD worker (spawned: it travels by this qualified name)."""
    from cadio.capture.scan import capture_step

    target, workspace, cfg = payload
    return capture_step(target, Path(workspace), cfg)


def _limits() -> Limits:
    """One CAD worker with the environment's per-file limits."""
    from flows.settings import load_settings

    return load_settings().limits(default_workers=1)


def cmd_export(args: argparse.Namespace) -> int:
    from collections import Counter

    from cadio.export.job import export_assemblies, model_digests, run_jobs, write_index
    from cadio.workspace import Workspace
    from flows.settings import runtime_settings
    from models.evaluate import SHIPPED
    from models.relate import SHIPPED_RELATIONS
    from reports.methods import product
    from reports.tables import printable

    config = args.config
    workspace, out = Path(config.runtime.workspace), config.out and Path(config.out)
    run_dir = Workspace(workspace).run_dir(config.run)
    models = model_digests({"relations": Path(config.models.relations or SHIPPED_RELATIONS),
                            "completion": Path(config.models.completion or SHIPPED)})
    try:
        jobs = run_jobs(workspace, run_dir, models, out, answers=product())
    except InputFileError as exc:
        print(f"mateqa export: {exc}", file=sys.stderr)
        return 2
    # in the command's own process the workers are the command's: 0 means one per core
    limits = runtime_settings(config.runtime).limits(default_workers=os.cpu_count() or 1)
    with progress("export", len(jobs)) as advance:
        summaries = []
        for summary in export_assemblies(jobs, limits):
            summaries.append(summary)
            advance(summary.assembly)
    index = write_index(out or run_dir.resolve() / "exports", summaries)
    for s in sorted(summaries, key=lambda s: s.assembly):
        print(f"{printable(s.assembly)}: {s.status}"  # names from input: one line each
              + (f" ({printable(s.reason)})" if s.reason else "")
              + (f", {s.predicted_pairs}/{s.pairs} pairs predicted, {s.constraints} "
                 "constraints" if s.sidecar and s.status != "failed" else ""))
    counts = Counter(s.status for s in summaries)
    print(f"{len(summaries)} assemblies ({', '.join(f'{n} {k}' for k, n in sorted(counts.items()))}"
          f"): {index}")
    return 0



def cmd_samples(args: argparse.Namespace) -> int:
    from cadio.samples.library import generate_library

    paths = generate_library(args.out)
    print(f"{len(paths)} STEP files in {args.out}")
    return 0
