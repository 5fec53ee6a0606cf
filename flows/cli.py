"""The ``mateqa`` command line.

``ingest``, ``mates`` and ``capture`` run the library functions directly (no Prefect);
``nightly`` runs the Prefect flow, against ``PREFECT_API_URL`` when set, otherwise against a
local Prefect server on SQLite that it starts (and leaves running for the UI and later runs
unless ``--stop-server``). Every command takes the same tolerance options (``--tol NAME=VALUE``,
``--tolerances FILE.json``), which map onto the one ``Tolerances`` object of the run.
Exit code 0 means the run completed, even when some inputs were bad (they are in the report);
``nightly`` exits 3 when the run completed but a per-category threshold failed or a metric
regressed (its report says which), 1 when the run itself failed, 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

from cadio.errors import InputFileError
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances, read_tolerances

if TYPE_CHECKING:
    from flows.settings import Settings

# Third-party loggers that narrate every operation at INFO (build123d logs each sketch step).
_CHATTY = ("httpx", "build123d")
# Prefect configures its own loggers when imported; this override (a default the user's
# environment may replace) keeps one "Finished in state Completed()" per task off the console:
# the flow logs one line per stage instead.
_PREFECT_QUIET = {"PREFECT_LOGGING_LOGGERS_PREFECT_TASK_RUNS_LEVEL": "WARNING"}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``mateqa`` command."""
    parser = _parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    for name in _CHATTY:
        logging.getLogger(name).setLevel(logging.WARNING)
    try:
        args.tolerances = _tolerances(args)
    except (ValueError, OSError) as exc:
        print(f"mateqa {args.command}: {exc}", file=sys.stderr)
        return 2
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        return 130


def _parser() -> argparse.ArgumentParser:
    # Imported here, not at the top: the CAD workers that ``ingest`` spawns import this module
    # afresh (multiprocessing re-runs the main module), and need neither pydantic nor pandas.
    from flows.settings import Settings

    parser = argparse.ArgumentParser(prog="mateqa", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    settings = Settings()

    p = sub.add_parser("ingest", help="read STEP files into a workspace catalog (no Prefect)",
                       description="Read every STEP file under DIR into the workspace: "
                       "catalog.parquet, meshes, features, voxels. Bad files become rows.")
    p.add_argument("library", type=Path, metavar="DIR", help="folder of STEP files")
    _common(p, settings)
    p.set_defaults(func=_cmd_ingest)

    p = sub.add_parser("nightly", help="run the nightly flow (the main job) with Prefect",
                       description="Run the nightly Prefect flow on a library (default: the "
                       "built-in sample library) against a local Prefect server on SQLite.")
    p.add_argument("--library", type=Path, default=None,
                   help="folder of STEP files, categories from its sub-folders, or a CSV with "
                   "columns path,category (default: generate the built-in sample library)")
    _common(p, settings)
    p.add_argument("--categories", nargs="+", default=None,
                   help="only these categories of the library")
    p.add_argument("--thresholds", type=Path, default=None,
                   help="per-category thresholds (TOML; default: reports/thresholds.toml)")
    p.add_argument("--history", type=int, default=7,
                   help="earlier runs the trends compare with (default 7)")
    p.add_argument("--no-fail-on-threshold", dest="fail_on_threshold", action="store_false",
                   help="exit 0 even when a threshold fails (the report still says so)")
    p.add_argument("--dask-address", default=None,
                   help="run the tasks on this Dask scheduler (tcp://host:8786)")
    p.add_argument("--pairs-per-relation", type=int, default=4,
                   help="scenes generated per relation (default 4)")
    p.add_argument("--views-per-scene", type=int, default=8,
                   help="views rendered per scene, spread over the 125-view circle (default 8)")
    p.add_argument("--noise", action="store_true", help="switch the depth noise model on")
    p.add_argument("--captures", type=Path, default=None,
                   help="folder of MCAP captures to read instead of rendering (real logs)")
    p.add_argument("--completion-models", type=Path, default=None,
                   help="folder of completion checkpoints (default: the shipped ones)")
    p.add_argument("--relation-models", type=Path, default=None,
                   help="folder of relation checkpoints (default: the shipped ones)")
    p.add_argument("--stop-server", action="store_true",
                   help="stop the local Prefect server this command started when done")
    p.set_defaults(func=_cmd_nightly)

    p = sub.add_parser("serve", help="a local Prefect server, work pool, worker and deployments",
                       description="Start a local Prefect server on SQLite (with its UI), a "
                       "process work pool with a worker, and apply the deployments of "
                       "prefect.yaml; then `prefect deployment run 'nightly/nightly' --watch` "
                       "works. Runs until interrupted (Ctrl-C or SIGTERM), then stops "
                       "everything it started.")
    p.add_argument("--port", type=int, default=settings.server_port,
                   help=f"server port (default {settings.server_port})")
    p.add_argument("--home", type=Path, default=settings.prefect_home,
                   help=f"Prefect home: database, logs (default {settings.prefect_home})")
    p.set_defaults(func=_cmd_serve, tol=[], tolerances_file=None)

    p = sub.add_parser("mates", help="face mates, relations and joints of a STEP assembly",
                       description="Extract the ground-truth mates of one STEP assembly into "
                       "WS/mates/<assembly>.parquet and print a summary.")
    p.add_argument("step", type=Path, metavar="STEP", help="a STEP assembly")
    _workspace_and_tolerances(p, settings)
    p.set_defaults(func=_cmd_mates)

    p = sub.add_parser("capture", help="render RGB-D views of a STEP file or a scene to MCAP",
                       description="Render RGB-D views (the paper's camera circle) of a STEP "
                       "part or assembly, or of a scene id of WS/scenes.parquet, into "
                       "WS/captures/<name>.mcap.")
    p.add_argument("target", metavar="STEP_OR_SCENE", nargs="?", help="a STEP file or a scene id")
    _workspace_and_tolerances(p, settings)
    p.add_argument("--views", type=int, default=125, help="views to render (default 125)")
    p.add_argument("--noise", action="store_true", help="switch the depth noise model on")
    p.add_argument("--read", type=Path, metavar="MCAP", default=None,
                   help="read a recording (ours, Foxglove or ROS 2) instead, and print what was "
                   "read: frames, topics, camera, pose and gravity sources, warnings")
    p.set_defaults(func=_cmd_capture)

    p = sub.add_parser("train", help="train the learned stages (completion, relations)",
                       description="Train the completion checkpoints on a corpus of generated "
                       "and real parts, or the relation networks on pairs of that corpus's "
                       "parts (after completion, in the same workspace); score them on "
                       "held-out parts beside the baselines, and write them with their model "
                       "card (no Prefect; the train flow runs the same steps).")
    p.add_argument("stage", choices=["completion", "relations"], help="what to train")
    p.add_argument("--workspace", type=Path, default=Path("train-workspace"),
                   help="training workspace: corpus, dataset, snapshots, reports")
    p.add_argument("--shared", type=Path, default=None,
                   help="folder of real STEP parts to add to the corpus (split by part)")
    p.add_argument("--variants", type=int, default=100,
                   help="parametric variants per category of the sample library")
    p.add_argument("--seed", type=int, default=0, help="seed of variants and splits")
    p.add_argument("--steps", type=int, default=2000, help="training steps per model")
    p.add_argument("--methods", nargs="+", default=None,
                   help="learned methods to train (default: gan_lstm ae r2n2 for completion, "
                   "ltn mlp for relations)")
    p.add_argument("--inputs", nargs="+", default=["truth", "partial", "completed"],
                   help="relations: the inputs to train a network for")
    p.add_argument("--pairs-per-relation", type=int, default=80,
                   help="relations: corpus scenes per relation (split by part)")
    p.add_argument("--protocols", nargs="+", default=["observed", "oracle-box"],
                   help="input protocols to train for")
    p.add_argument("--out", type=Path, default=None,
                   help="checkpoint folder (default: the shipped models/checkpoints/<stage>)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                   help="worker processes for CAD work and rendering")
    p.add_argument("--grids", type=int, nargs=2, default=[32, 64], metavar=("N_IN", "N_OUT"),
                   help="input and output grid sides (default 32 64; the paper's 64 256 is for "
                   "a GPU, in its own workspace)")
    p.add_argument("--lr", type=float, default=1e-3,
                   help="Adam learning rate of the networks (the paper's 1e-4 suits long GPU runs)")
    p.add_argument("--lr-critic", type=float, default=1e-4,
                   help="Adam learning rate of gan_lstm's critic")
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads (one is fastest on a busy 2-core machine)")
    p.set_defaults(func=_cmd_train, tol=[], tolerances_file=None)

    p = sub.add_parser("export", help="write a run's predicted mates back into CAD files "
                       "(no Prefect)",
                       description="For every assembly of a run: an XBF document with XDE "
                       "notes, a sidecar JSON (schema: cadio/export/mates.schema.json) and a "
                       "CadQuery constraint script, under RUN/exports/ASSEMBLY/ (or --out), "
                       "with exports/index.csv listing each assembly's status.")
    p.add_argument("--workspace", type=Path, default=settings.workspace,
                   help=f"workspace folder (default {settings.workspace})")
    p.add_argument("--run", default="latest",
                   help="the run whose predictions to export: a run id or 'latest'")
    p.add_argument("--out", type=Path, default=None,
                   help="folder for the exports (default RUN/exports)")
    p.add_argument("--relation-models", type=Path, default=None,
                   help="relation checkpoints the run used (default: the shipped ones)")
    p.add_argument("--completion-models", type=Path, default=None,
                   help="completion checkpoints the run used (default: the shipped ones)")
    p.add_argument("--workers", type=int, default=settings.workers,
                   help="parallel CAD worker processes (0 = one per core)")
    p.set_defaults(func=_cmd_export, tol=[], tolerances_file=None)

    p = sub.add_parser("samples", help="generate the built-in sample library",
                       description="Write the built-in sample STEP library into OUT.")
    p.add_argument("out", type=Path, metavar="OUT", help="output folder")
    p.set_defaults(func=_cmd_samples, tol=[], tolerances_file=None)
    return parser


def _workspace_and_tolerances(p: argparse.ArgumentParser, settings: Settings) -> None:
    p.add_argument("--workspace", type=Path, default=settings.workspace,
                   help=f"workspace folder (default {settings.workspace})")
    p.add_argument("--tol", action="append", default=[], metavar="NAME=VALUE",
                   help="override one tolerance (repeatable), e.g. --tol contact_mm=0.2; "
                   f"names: {', '.join(DEFAULT_TOLERANCES.as_dict())}")
    p.add_argument("--tolerances", dest="tolerances_file", type=Path, default=None,
                   metavar="FILE", help="JSON object of tolerance overrides (a run's "
                   "tolerances.json reads back); --tol applies on top")


def _common(p: argparse.ArgumentParser, settings: Settings) -> None:
    _workspace_and_tolerances(p, settings)
    p.add_argument("--voxel-sizes", type=int, nargs="+", default=None,
                   help="occupancy grid sizes (default 32 64)")
    p.add_argument("--workers", type=int, default=settings.workers,
                   help="parallel CAD worker processes (0 = one per core)")
    p.add_argument("--timeout", type=float, default=settings.file_timeout_s,
                   help="seconds allowed per file before its worker is killed")
    p.add_argument("--memory-mb", type=int, default=settings.file_memory_mb,
                   help="address-space limit of each worker process, MB")
    p.add_argument("--max-file-mb", type=float, default=settings.max_file_mb,
                   help="files larger than this are skipped, MB")


def _tolerances(args: argparse.Namespace) -> Tolerances:
    """The run's tolerances: the defaults, then ``--tolerances FILE``, then each ``--tol``."""
    tol = read_tolerances(args.tolerances_file) if args.tolerances_file else DEFAULT_TOLERANCES
    overrides = {}
    for item in args.tol:
        name, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--tol takes NAME=VALUE, got {item!r}")
        overrides[name.strip()] = value.strip()
    return tol.with_overrides(overrides)


@contextmanager
def _progress(description: str, total: int | None) -> Iterator[Callable[[str], None]]:
    """A progress bar on stderr (a counter when ``total`` is None); yields the function that
    advances it by one item."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    columns = (*Progress.get_default_columns()[:1], BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn())
    with Progress(*columns, transient=True) as bar:
        task = bar.add_task(description, total=total)
        yield lambda item: bar.advance(task)


def _cmd_ingest(args: argparse.Namespace) -> int:
    from cadio.cad.ingest import discover, ingest
    from flows.settings import Settings, ingest_config
    from reports.render import build_ingest_report

    settings = Settings(workers=args.workers, file_timeout_s=args.timeout,
                        file_memory_mb=args.memory_mb, max_file_mb=args.max_file_mb)
    cfg = ingest_config(settings, args.voxel_sizes, args.tolerances,
                        default_workers=os.cpu_count() or 1)
    try:
        total = len(discover(args.library))
        with _progress("ingest", total) as advance:
            catalog = ingest(args.library, args.workspace, cfg, on_file=advance)
    except InputFileError as exc:
        print(f"mateqa ingest: {exc}", file=sys.stderr)
        return 2
    print(build_ingest_report(catalog).markdown())
    print(f"catalog: {Path(args.workspace) / 'catalog.parquet'}")
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    if args.stage == "relations":
        return _cmd_train_relations(args)
    import shlex
    import time

    import torch

    from cadio.cad.ingest import IngestConfig
    from cadio.capture.corpus import CorpusConfig
    from cadio.capture.examples import ExampleConfig
    from cadio.sandbox import Limits
    from cadio.workspace import Workspace
    from flows.train import evaluate_models, prepare_corpus, train_model, write_model_card
    from models.evaluate import SHIPPED

    torch.set_num_threads(args.threads)
    ws = Workspace(args.workspace.resolve())
    out = (args.out or SHIPPED).resolve()
    ingest_cfg = IngestConfig(limits=Limits(workers=args.workers, seconds=600),
                              tolerances=args.tolerances)
    try:
        with _progress("corpus parts", None) as advance:
            corpus = prepare_corpus(ws, args.shared, args.variants, args.seed, ingest_cfg,
                                    CorpusConfig(example=ExampleConfig(
                n_in=args.grids[0], n_out=args.grids[1],
                grid_margin=args.tolerances.grid_margin), seed=args.seed), advance)
    except (InputFileError, ValueError) as exc:
        print(f"mateqa train: {exc}", file=sys.stderr)
        return 2
    print(f"corpus: {corpus.parts} parts {corpus.splits}, {corpus.failed} failed")
    for protocol in args.protocols:
        for method in args.methods or ["gan_lstm", "ae", "r2n2"]:
            with _progress(f"{method}/{protocol}", args.steps) as advance:
                trained = train_model(ws, method, protocol, args.steps, out,
                                      on_step=lambda *a: advance(""),
                                      rates={"lr": args.lr, "lr_d": args.lr_critic},
                                      n_in=args.grids[0], n_out=args.grids[1])
            print(f"{method}/{protocol}: best val IoU {trained.val_iou:.3f} at step "
                  f"{trained.step} ({trained.seconds:.0f} s) -> {trained.path}")
    run_dir = ws.run_dir(time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()))
    evaluate_models(ws, out, run_dir)
    command = "mateqa " + shlex.join(args.argv)
    card = write_model_card(ws, out, run_dir, command,
                            {"steps": args.steps, "variants": args.variants, "seed": args.seed,
                             "threads": args.threads}, corpus)
    print(Path(run_dir / "completion.md").read_text())
    print(f"model card: {card}")
    return 0


def _cmd_train_relations(args: argparse.Namespace) -> int:
    import shlex
    import time

    import torch

    from cadio.sandbox import Limits
    from cadio.workspace import Workspace
    from flows.train_relations import (
        build_dataset,
        evaluate_relations,
        train_relation_model,
        write_relation_card,
    )
    from models.evaluate import SHIPPED
    from models.relate import SHIPPED_RELATIONS

    torch.set_num_threads(args.threads)
    ws = Workspace(args.workspace.resolve())
    out = (args.out or SHIPPED_RELATIONS).resolve()
    try:
        with _progress("labelled shots", None) as advance:
            rows = build_dataset(ws, SHIPPED, Limits(workers=args.workers, seconds=600),
                                 advance)
    except (FileNotFoundError, ValueError) as exc:
        print(f"mateqa train relations: {exc} (run mateqa train completion in this workspace "
              "first)", file=sys.stderr)
        return 2
    print(f"pair views per split {rows}")
    for name in args.inputs:
        for method in args.methods or ["ltn", "mlp"]:
            with _progress(f"{method}/{name}", args.steps) as advance:
                trained = train_relation_model(ws, method, name, args.steps, out,
                                               on_step=lambda: advance(""))
            print(f"{method}/{name}: best val accuracy {trained.val_accuracy:.4f} at step "
                  f"{trained.step} ({trained.seconds:.0f} s) -> {trained.path}")
    run_dir = ws.run_dir(time.strftime("relations-%Y%m%dT%H%M%SZ", time.gmtime()))
    report = evaluate_relations(ws, out, run_dir)
    card = write_relation_card(ws, out, run_dir, "mateqa " + shlex.join(args.argv),
                               {"steps": args.steps, "seed": args.seed,
                                "pairs_per_relation": args.pairs_per_relation})
    print(report.read_text())
    print(f"model card: {card}")
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
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
    with _progress("export", len(jobs)) as advance:
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


def _cmd_samples(args: argparse.Namespace) -> int:
    from cadio.samples.library import generate_library

    paths = generate_library(args.out)
    print(f"{len(paths)} STEP files in {args.out}")
    return 0


def _cmd_mates(args: argparse.Namespace) -> int:
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


def _cmd_capture(args: argparse.Namespace) -> int:
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
        with _progress("capture", args.views) as advance:
            summary = capture_step(args.target, args.workspace, cfg, on_frame=advance)
    except InputFileError as exc:
        print(f"mateqa capture: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary.to_dict(), indent=1))
    return 0


def _cmd_nightly(args: argparse.Namespace) -> int:
    from flows.server import server_env, start_server, stop_server
    from flows.settings import Settings
    from reports.trends import DEFAULT_THRESHOLDS, ThresholdsError, read_thresholds

    try:  # a bad thresholds file is a bad argument: say so before any work
        read_thresholds(args.thresholds or DEFAULT_THRESHOLDS)
    except ThresholdsError as exc:
        print(f"mateqa nightly: {exc}", file=sys.stderr)
        return 2

    settings = Settings()
    proc = None
    for key, value in _PREFECT_QUIET.items():
        os.environ.setdefault(key, value)
    if "PREFECT_API_URL" not in os.environ:
        home = settings.prefect_home
        os.environ.update(server_env(home, settings.server_port))
        print(f"starting a local Prefect server on SQLite in {home} ...", flush=True)
        proc = start_server(home, settings.server_port)
        print(f"Prefect API at {os.environ['PREFECT_API_URL']}", flush=True)
    try:
        return _run_nightly(args)
    finally:
        if args.stop_server:
            stop_server(proc)


def _cmd_serve(args: argparse.Namespace) -> int:
    import signal
    import threading

    from flows.server import (
        api_url,
        apply_deployments,
        project_root,
        server_env,
        start_server,
        start_worker,
        stop_process,
    )

    root, home = project_root(), args.home.resolve()
    env = server_env(home, args.port, ui=True)
    env.update({k: env.get(k, v) for k, v in _PREFECT_QUIET.items()})
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    server = worker = None
    try:
        print(f"starting a local Prefect server on SQLite in {home} ...", flush=True)
        server = start_server(home, args.port, ui=True)
        apply_deployments(env, root, home / "deploy.log")
        worker = start_worker(env, root, home / "worker.log")
        print(f"Prefect UI:  http://127.0.0.1:{args.port}\nPrefect API: {api_url(args.port)}\n"
              f"work pool 'mateqa' with a process worker (log: {home / 'worker.log'})\n"
              f"deployments of {root / 'prefect.yaml'} applied; run the nightly with\n"
              f"  PREFECT_API_URL={api_url(args.port)} prefect deployment run 'nightly/nightly'"
              f" --param library=DIR --watch\nCtrl-C stops the worker and the server.",
              flush=True)
        while not stop.wait(1.0):
            if worker.poll() is not None:
                print(f"mateqa serve: the worker stopped (exit {worker.returncode}); see "
                      f"{home / 'worker.log'}", file=sys.stderr)
                return 1
        return 0
    except RuntimeError as exc:
        print(f"mateqa serve: {exc}", file=sys.stderr)
        return 1
    finally:
        stop_process(worker)
        stop_process(server)
        print("mateqa serve: stopped", flush=True)


def _run_nightly(args: argparse.Namespace) -> int:
    from flows.nightly import ThresholdFailure, nightly

    state = nightly(
        library=str(args.library) if args.library else None,
        workspace=str(args.workspace),
        tolerances=args.tolerances,
        voxel_sizes=args.voxel_sizes,
        pairs_per_relation=args.pairs_per_relation,
        views_per_scene=args.views_per_scene,
        noise=args.noise,
        captures=str(args.captures) if args.captures else None,
        completion_models=str(args.completion_models) if args.completion_models else None,
        relation_models=str(args.relation_models) if args.relation_models else None,
        categories=args.categories,
        thresholds=str(args.thresholds) if args.thresholds else None,
        history=args.history,
        fail_on_threshold=args.fail_on_threshold,
        dask_address=args.dask_address,
        workers=args.workers or 1,
        file_timeout_s=args.timeout,
        file_memory_mb=args.memory_mb,
        max_file_mb=args.max_file_mb,
        return_state=True,
    )
    if not state.is_completed():
        failure = state.result(raise_on_failure=False)
        if isinstance(failure, ThresholdFailure):
            print(Path(failure.run_dir, "report.md").read_text())
            print(f"mateqa nightly: {failure}", file=sys.stderr)
            return 3
        print(f"mateqa nightly: the run failed: {state.message}", file=sys.stderr)
        return 1
    summary = state.result()
    print(Path(summary.ingest_report).read_text())
    print(Path(summary.stages_report).read_text())
    print(Path(summary.completion_report).read_text())
    print(Path(summary.relations_report).read_text())
    print(json.dumps(asdict(summary), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
