"""The ``mateqa`` command line.

``ingest``, ``mates`` and ``capture`` run the library functions directly (no Prefect);
``nightly`` runs the Prefect flow, against ``PREFECT_API_URL`` when set, otherwise against a
local Prefect server on SQLite with its UI that it starts (and leaves running for the UI and
later runs unless ``--stop-server``; ``serve --stop`` stops it). ``nightly``, ``ingest``,
``mates`` and ``capture`` take the same tolerance options (``--tol NAME=VALUE``,
``--tolerances FILE.json``), which map onto the one ``Tolerances`` object of the run.
``train`` writes into its training workspace; ``ship`` makes those checkpoints the default.
Exit code 0 means the run completed, even when some inputs were bad (they are in the report);
``nightly`` exits 3 when the run completed but a per-category threshold failed or a metric
regressed (its report says which), 1 when the run itself failed, 2 on bad arguments. It ends
with the night's verdict in a dozen lines (``reports.verdict``), or with ``--json`` the run's
full ``summary.json``.

This module holds the parser; the commands live beside it: ``cli_cad`` (ingest, mates, capture,
export, samples), ``cli_train`` (train, ship), ``cli_nightly`` (nightly, serve) and
``cli_thresholds`` (thresholds calibrate: floors from a healthy night).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from cadio.tolerances import DEFAULT_TOLERANCES
from flows.cli_cad import cmd_capture, cmd_export, cmd_ingest, cmd_mates, cmd_samples
from flows.cli_nightly import cmd_nightly, cmd_serve
from flows.cli_options import allowed, bounded, check_inputs, config_of, tolerances_of
from flows.cli_thresholds import add_thresholds_parser
from flows.cli_train import cmd_ship, cmd_train

if TYPE_CHECKING:
    from flows.settings import Settings

# Third-party loggers that narrate every operation at INFO (build123d logs each sketch step).
_CHATTY = ("httpx", "build123d")


class _Parser(argparse.ArgumentParser):
    """argparse, except that a bad option is one line (the command, the option, the reason)
    rather than the usage block."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``mateqa`` command."""
    from flows.settings import SettingsError

    try:
        parser = _parser()
    except SettingsError as exc:
        print(f"mateqa: environment: {exc}", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    for name in _CHATTY:
        logging.getLogger(name).setLevel(logging.WARNING)
    try:  # every option and settings file, before any work
        args.tolerances = tolerances_of(args)
        args.config = config_of(args)
        warnings = check_inputs(args)
    except (ValueError, OSError) as exc:
        print(f"mateqa {args.command}: {exc}", file=sys.stderr)
        return 2
    for warning in warnings:
        print(f"mateqa {args.command}: warning: {warning}", file=sys.stderr)
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        return 130


def _parser() -> argparse.ArgumentParser:
    # Imported here, not at the top: importing this module (as ``python -m flows.cli`` and
    # the tests do) needs neither pydantic nor pandas.
    from flows.settings import load_settings

    parser = _Parser(prog="mateqa", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    settings = load_settings()

    p = sub.add_parser("ingest", help="read STEP files into a workspace catalog (no Prefect)",
                       description="Read every STEP file under DIR into the workspace: "
                       "catalog.parquet, meshes, features, voxels. Bad files become rows.")
    p.add_argument("library", type=Path, metavar="DIR", help="folder of STEP files")
    _common(p, settings)
    p.set_defaults(func=cmd_ingest)

    p = sub.add_parser("nightly", help="run the nightly flow (the main job) with Prefect",
                       description="Run the nightly Prefect flow on a library (default: the "
                       "built-in sample library) against a local Prefect server on SQLite.")
    p.add_argument("--library", type=Path, default=None,
                   help="folder of STEP files, categories from its sub-folders, or a CSV with "
                   "columns path,category (default: generate the built-in sample library)")
    _common(p, settings)
    p.add_argument("--categories", nargs="+", default=None,
                   help="only these categories of the library (each must be one it has)")
    p.add_argument("--thresholds", type=Path, default=None,
                   help="per-category thresholds (TOML; default: reports/thresholds.toml)")
    p.add_argument("--history", type=int, default=7,
                   help="earlier runs the trends compare with (default 7)"
                   + allowed("thresholds.history"))
    p.add_argument("--no-fail-on-threshold", dest="fail_on_threshold", action="store_false",
                   help="exit 0 even when a threshold fails (the report still says so)")
    p.add_argument("--dask-address", default=None,
                   help="run the tasks on this Dask scheduler (tcp://host:8786)")
    p.add_argument("--pairs-per-relation", type=int, default=4,
                   help="scenes generated per relation (default 4)"
                   + allowed("capture.pairs_per_relation"))
    p.add_argument("--views-per-scene", type=int, default=8,
                   help="views rendered per scene, spread over the 125-view circle (default 8)"
                   + allowed("capture.views_per_scene"))
    p.add_argument("--noise", action="store_true", help="switch the depth noise model on")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the scene generator (default 0)" + allowed("capture.seed"))
    p.add_argument("--batch-size", type=int, default=12,
                   help="files per ingest task (default 12)" + allowed("library.batch_size"))
    p.add_argument("--captures", type=Path, default=None,
                   help="folder of MCAP recordings to read instead of rendering (real logs); "
                   "it must hold at least one")
    p.add_argument("--completion-models", type=Path, default=None,
                   help="folder of completion checkpoints, each loaded before the night starts "
                   "(default: the shipped ones)")
    p.add_argument("--relation-models", type=Path, default=None,
                   help="folder of relation checkpoints, each loaded before the night starts "
                   "(default: the shipped ones)")
    p.add_argument("--stop-server", action="store_true",
                   help="stop the local Prefect server this command started when done")
    p.add_argument("--json", action="store_true",
                   help="print the run's full summary (its summary.json) instead of the verdict")
    p.set_defaults(func=cmd_nightly)

    p = sub.add_parser("serve", help="a local Prefect server, work pool, worker and deployments",
                       description="Start a local Prefect server on SQLite (with its UI), a "
                       "process work pool with a worker, and apply the deployments of "
                       "prefect.yaml; then `prefect deployment run 'nightly/nightly' --watch` "
                       "works. It takes over the server a night left running (a server without "
                       "a UI is replaced). Runs until interrupted (Ctrl-C or SIGTERM), then "
                       "stops the worker and that server; --stop stops a server left running.")
    p.add_argument("--port", type=bounded(int, 1, 65535), default=settings.server_port,
                   help=f"server port (default {settings.server_port})")
    p.add_argument("--home", type=Path, default=settings.prefect_home,
                   help=f"Prefect home: database, logs (default {settings.prefect_home})")
    p.add_argument("--stop", action="store_true",
                   help="stop the Prefect server on the port (the one a night left running) "
                   "and exit")
    p.set_defaults(func=cmd_serve, tol=[], tolerances_file=None)

    p = sub.add_parser("mates", help="face mates, relations and joints of a STEP assembly",
                       description="Extract the ground-truth mates of one STEP assembly into "
                       "WS/mates/<assembly>.parquet and print a summary.")
    p.add_argument("step", type=Path, metavar="STEP", help="a STEP assembly")
    _workspace_and_tolerances(p, settings)
    p.set_defaults(func=cmd_mates)

    p = sub.add_parser("capture", help="render RGB-D views of a STEP file or a scene to MCAP",
                       description="Render RGB-D views (the paper's camera circle) of a STEP "
                       "part or assembly, or of a scene id of WS/scenes.parquet, into "
                       "WS/captures/<name>.mcap.")
    p.add_argument("target", metavar="STEP_OR_SCENE", nargs="?", help="a STEP file or a scene id")
    _workspace_and_tolerances(p, settings)
    p.add_argument("--views", type=int, default=125, help="views to render (default 125)"
                   + allowed("capture.views_per_scene"))
    p.add_argument("--noise", action="store_true", help="switch the depth noise model on")
    p.add_argument("--read", type=Path, metavar="MCAP", default=None,
                   help="read a recording (ours, Foxglove or ROS 2) instead, and print what was "
                   "read: frames, topics, camera, pose and gravity sources, warnings")
    p.set_defaults(func=cmd_capture)

    p = sub.add_parser("train", help="train the learned stages (completion, relations)",
                       description="Train the completion checkpoints on a corpus of generated "
                       "and real parts, or the relation networks on pairs of that corpus's "
                       "parts (after completion, in the same workspace); score them on "
                       "held-out parts beside the baselines, and write them with their model "
                       "card (no Prefect; the train flow runs the same steps).")
    _training_workspace(p, "what to train", "checkpoint folder (default: "
                        "WORKSPACE/checkpoints/<stage>)")
    p.add_argument("--shared", type=Path, default=None,
                   help="folder of real STEP parts to add to the corpus (split by part)")
    p.add_argument("--variants", type=bounded(int, 0, 100_000), default=100,
                   help="parametric variants per category of the sample library")
    p.add_argument("--seed", type=bounded(int, 0, 2**32 - 1), default=0,
                   help="seed of variants and splits")
    p.add_argument("--steps", type=bounded(int, 1, 10_000_000), default=2000,
                   help="training steps per model")
    p.add_argument("--methods", nargs="+", default=None,
                   help="learned methods to train (default: gan_lstm ae r2n2 for completion, "
                   "ltn mlp for relations)")
    p.add_argument("--inputs", nargs="+", default=["truth", "partial", "completed"],
                   help="relations: the inputs to train a network for")
    p.add_argument("--pairs-per-relation", type=bounded(int, 1, 100_000), default=150,
                   help="completion: the corpus's pair scenes per relation (split by part)")
    p.add_argument("--contact-pairs", type=bounded(int, 0, 100_000), default=0,
                   help="completion: pair scenes of parts touching at random orientations, "
                   "seldom a face mate (none by default: see the relation model card)")
    p.add_argument("--clearance-pairs", type=bounded(int, 0, 100_000), default=0,
                   help="completion: pair scenes of two parts on one axis 1.5 to 4 mm apart, "
                   "coaxial without a concentric mate (none by default)")
    p.add_argument("--protocols", nargs="+", default=["observed", "oracle-box"],
                   help="input protocols to train for")
    p.add_argument("--workers", type=bounded(int, 1, 256), default=os.cpu_count() or 1,
                   help="worker processes for CAD work and rendering")
    p.add_argument("--grids", type=bounded(int, 8, 512), nargs=2, default=[32, 64],
                   metavar=("N_IN", "N_OUT"),
                   help="input and output grid sides (default 32 64; the paper's 64 256 is for "
                   "a GPU, in its own workspace)")
    p.add_argument("--lr", type=bounded(float, 1e-9, 1.0), default=1e-3,
                   help="Adam learning rate of the networks (the paper's 1e-4 suits long GPU runs)")
    p.add_argument("--lr-critic", type=bounded(float, 1e-9, 1.0), default=1e-4,
                   help="Adam learning rate of gan_lstm's critic")
    p.add_argument("--threads", type=bounded(int, 1, 256), default=1,
                   help="torch threads (one is fastest on a busy 2-core machine)")
    p.set_defaults(func=cmd_train, tol=[], tolerances_file=None)

    p = sub.add_parser("ship", help="make trained checkpoints the shipped default",
                       description="Copy the checkpoints `mateqa train STAGE` wrote into its "
                       "workspace, with their MODEL_CARD.md, over the shipped ones "
                       "(models/checkpoints/STAGE), which a night uses unless told otherwise. "
                       "Read the model card first.")
    _training_workspace(p, "what to ship", "the folder train wrote to, when it was given --out")
    p.set_defaults(func=cmd_ship, tol=[], tolerances_file=None)

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
                   help="parallel CAD worker processes (0 = one per core)"
                   + allowed("runtime.workers"))
    p.set_defaults(func=cmd_export, tol=[], tolerances_file=None)

    add_thresholds_parser(sub)

    p = sub.add_parser("samples", help="generate the built-in sample library",
                       description="Write the built-in sample STEP library into OUT.")
    p.add_argument("out", type=Path, metavar="OUT", help="output folder")
    p.set_defaults(func=cmd_samples, tol=[], tolerances_file=None)
    return parser


def _training_workspace(p: argparse.ArgumentParser, stage_help: str, out_help: str) -> None:
    p.add_argument("stage", choices=["completion", "relations"], help=stage_help)
    p.add_argument("--workspace", type=Path, default=Path("train-workspace"),
                   help="training workspace: corpus, dataset, snapshots, reports, checkpoints "
                   "(default train-workspace)")
    p.add_argument("--out", type=Path, default=None, help=out_help)


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
                   help="occupancy grid sizes (default 32 64)" + allowed("library.voxel_sizes"))
    p.add_argument("--workers", type=int, default=settings.workers,
                   help="parallel CAD worker processes (ingest: 0 = one per core; nightly: "
                   "per task, 0 = one)" + allowed("runtime.workers"))
    p.add_argument("--timeout", type=float, default=settings.file_timeout_s,
                   help="seconds allowed per file before its worker is killed"
                   + allowed("runtime.file_timeout_s"))
    p.add_argument("--memory-mb", type=int, default=settings.file_memory_mb,
                   help="address-space limit of each worker process, MB"
                   + allowed("runtime.file_memory_mb"))
    p.add_argument("--max-file-mb", type=float, default=settings.max_file_mb,
                   help="files larger than this are skipped, MB" + allowed("runtime.max_file_mb"))


if __name__ == "__main__":
    sys.exit(main())
