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

from cadio.errors import InputFileError


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
    from flows.settings import Settings, ingest_config
    from reports.render import build_ingest_report

    settings = Settings(workers=args.workers, file_timeout_s=args.timeout,
                        file_memory_mb=args.memory_mb, max_file_mb=args.max_file_mb)
    cfg = ingest_config(settings, args.voxel_sizes, args.tolerances,
                        default_workers=os.cpu_count() or 1)
    try:
        total = len(discover(args.library))
        with progress("ingest", total) as advance:
            catalog = ingest(args.library, args.workspace, cfg, on_file=advance)
    except InputFileError as exc:
        print(f"mateqa ingest: {exc}", file=sys.stderr)
        return 2
    print(build_ingest_report(catalog).markdown())
    print(f"catalog: {Path(args.workspace) / 'catalog.parquet'}")
    return 0



def cmd_mates(args: argparse.Namespace) -> int:
    from cadio.truth.mates import read_assembly_mates, write_mates
    from cadio.workspace import Workspace

    try:
        result = read_assembly_mates(args.step, args.tolerances)
    except InputFileError as exc:
        print(f"mateqa mates: {exc}", file=sys.stderr)
        return 2
    out = Workspace(args.workspace).mates(args.step.stem)
    write_mates(out, result.table)
    counts = result.table.groupby(["level", "relation"]).size()
    print(f"{result.n_parts} parts, {result.n_pairs} pairs, {result.n_contact_pairs} in contact")
    print(counts.to_string())
    print(f"mates: {out}")
    return 0



def cmd_capture(args: argparse.Namespace) -> int:
    from cadio.capture.mcap_io import summarise_capture
    from cadio.capture.scan import ScanConfig, capture_step

    if args.read is not None:
        read = summarise_capture(args.read)
        print(json.dumps(read.to_dict(), indent=1))
        return 2 if read.error else 0
    if args.target is None:
        print("mateqa capture: give STEP_OR_SCENE, or --read MCAP", file=sys.stderr)
        return 2
    cfg = ScanConfig(views_per_scene=args.views, noise=args.noise, tolerances=args.tolerances)
    try:
        with progress("capture", args.views) as advance:
            summary = capture_step(args.target, args.workspace, cfg, on_frame=advance)
    except InputFileError as exc:
        print(f"mateqa capture: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary.to_dict(), indent=1))
    return 0



def cmd_export(args: argparse.Namespace) -> int:
    from collections import Counter

    from cadio.export.job import export_assemblies, model_digests, run_jobs, write_index
    from cadio.sandbox import Limits
    from cadio.workspace import Workspace
    from models.evaluate import SHIPPED
    from models.relate import SHIPPED_RELATIONS

    run_dir = Workspace(args.workspace).run_dir(args.run)
    models = model_digests({"relations": args.relation_models or SHIPPED_RELATIONS,
                            "completion": args.completion_models or SHIPPED})
    try:
        jobs = run_jobs(args.workspace, run_dir, models, args.out)
    except InputFileError as exc:
        print(f"mateqa export: {exc}", file=sys.stderr)
        return 2
    workers = args.workers or os.cpu_count() or 1
    with progress("export", len(jobs)) as advance:
        summaries = []
        for summary in export_assemblies(jobs, Limits(workers=workers)):
            summaries.append(summary)
            advance(summary.assembly)
    index = write_index(args.out or run_dir.resolve() / "exports", summaries)
    for s in sorted(summaries, key=lambda s: s.assembly):
        print(f"{s.assembly}: {s.status}" + (f" ({s.reason})" if s.reason else "")
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
