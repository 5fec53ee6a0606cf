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
export, samples), ``cli_train`` (train, ship), ``cli_nightly`` (nightly, serve),
``cli_thresholds`` (thresholds calibrate: floors from a healthy night) and ``cli_inspect``
(inspect: one recording of an assembly against its design).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from cadio.camera import CIRCLE_VIEWS
from cadio.tolerances import DEFAULT_TOLERANCES
from flows.cli_cad import cmd_capture, cmd_export, cmd_ingest, cmd_mates, cmd_samples
from flows.cli_inspect import add_inspect_parser
from flows.cli_nightly import cmd_nightly, cmd_serve
from flows.cli_options import (
    add_config_options,
    bounded,
    check_inputs,
    config_of,
    tolerances_of,
)
from flows.cli_schedule import add_schedule_parser
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
    _ingest_command(sub)
    _nightly_command(sub)
    _serve_command(sub, settings)
    add_schedule_parser(sub, _tolerances)
    _mates_command(sub, settings)
    _capture_command(sub, settings)
    _train_command(sub)
    _ship_command(sub)
    _export_command(sub)
    add_thresholds_parser(sub)
    add_inspect_parser(sub, settings.workspace)
    _samples_command(sub)
    return parser


def _ingest_command(sub: Any) -> None:
    p = sub.add_parser("ingest", help="read STEP files into a workspace catalog (no Prefect)",
                       description="Read every STEP file under DIR into the workspace: "
                       "catalog.parquet, meshes, features, voxels. Bad files become rows.")
    add_config_options(p, "ingest")
    _tolerances(p)
    p.set_defaults(func=cmd_ingest)


def _nightly_command(sub: Any) -> None:
    p = sub.add_parser("nightly", help="run the nightly flow (the main job) with Prefect",
                       description="Run the nightly Prefect flow on a library (default: the "
                       "built-in sample library) against a local Prefect server on SQLite. "
                       "Every option is a field of the night's configuration "
                       "(flows/config.py, NightConfig), which a deployment takes too.")
    add_config_options(p, "nightly")
    _tolerances(p)
    p.add_argument("--stop-server", action="store_true",
                   help="stop the local Prefect server this command started when done")
    p.add_argument("--json", action="store_true",
                   help="print the run's full summary (its summary.json) instead of the verdict")
    p.set_defaults(func=cmd_nightly)


def _serve_command(sub: Any, settings: Settings) -> None:
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


def _mates_command(sub: Any, settings: Settings) -> None:
    p = sub.add_parser("mates", help="face mates, relations and joints of a STEP assembly",
                       description="Extract the ground-truth mates of one STEP assembly into "
                       "WS/mates/<assembly>.parquet and print a summary.")
    p.add_argument("step", type=Path, metavar="STEP", help="a STEP assembly")
    _workspace(p, settings)
    _tolerances(p)
    p.set_defaults(func=cmd_mates)


def _capture_command(sub: Any, settings: Settings) -> None:
    p = sub.add_parser("capture", help="render RGB-D views of a STEP file or a scene to MCAP",
                       description="Render RGB-D views (the paper's camera circle) of a STEP "
                       "part or assembly, or of a scene id of WS/scenes.parquet, into "
                       "WS/captures/<name>.mcap.")
    p.add_argument("target", metavar="STEP_OR_SCENE", nargs="?", help="a STEP file or a scene id")
    _workspace(p, settings)
    _tolerances(p)
    circle = CIRCLE_VIEWS
    p.add_argument("--views", type=int, default=circle,
                   help=f"views to render, spread over the circle (default: all {circle}, "
                   f"the paper's circle; allowed: 1 to {circle})")
    p.add_argument("--noise", action="store_true", help="switch the depth noise model on")
    p.add_argument("--read", type=Path, metavar="MCAP", default=None,
                   help="read a recording (ours, Foxglove or ROS 2) instead, and print what was "
                   "read: frames, topics, camera, pose and gravity sources, warnings")
    p.set_defaults(func=cmd_capture)


def _train_command(sub: Any) -> None:
    p = sub.add_parser("train", help="train the learned stages (completion, relations)",
                       description="Train the completion checkpoints on a corpus of generated "
                       "and real parts, or the relation networks on pairs of that corpus's "
                       "parts (after completion in the same workspace, or on a corpus of their "
                       "own where it has none); score them on held-out parts beside the "
                       "baselines, and write them with their model card (no Prefect; the train "
                       "flow runs the same steps with the same configuration, "
                       "models/training/config.py).")
    p.add_argument("stage", choices=["completion", "relations"], help="what to train")
    add_config_options(p, "train")
    p.add_argument("--steps", type=bounded(int, 1, 10_000_000), default=None,
                   help="training steps per network of the stage (its --completion-steps or "
                   "--relation-steps)")
    p.add_argument("--methods", nargs="+", default=None,
                   help="the stage's networks to train (its --completion-methods or "
                   "--relation-methods)")
    p.add_argument("--out", type=Path, default=None, help="the stage's checkpoint folder (its "
                   "--completion-out or --relation-out)")
    p.set_defaults(func=cmd_train, tol=[], tolerances_file=None)


def _ship_command(sub: Any) -> None:
    p = sub.add_parser("ship", help="make trained checkpoints the shipped default",
                       description="Copy the checkpoints `mateqa train STAGE` wrote into its "
                       "workspace, with their MODEL_CARD.md, over the shipped ones "
                       "(models/checkpoints/STAGE), which a night uses unless told otherwise. "
                       "Read the model card first.")
    p.add_argument("stage", choices=["completion", "relations"], help="what to ship")
    from models.training.config import TrainConfig

    p.add_argument("--workspace", type=Path, default=Path(TrainConfig.model_fields[
        "workspace"].default), help="the training workspace")
    p.add_argument("--out", type=Path, default=None,
                   help="the folder train wrote to, when it was given --out")
    p.set_defaults(func=cmd_ship, tol=[], tolerances_file=None)


def _export_command(sub: Any) -> None:
    p = sub.add_parser("export", help="write a run's predicted mates back into CAD files "
                       "(no Prefect)",
                       description="For every assembly of a run: an XBF document with XDE "
                       "notes, a sidecar JSON (schema: cadio/export/mates.schema.json) and a "
                       "CadQuery constraint script, under RUN/exports/ASSEMBLY/ (or --out), "
                       "with exports/index.csv listing each assembly's status.")
    add_config_options(p, "export")
    p.set_defaults(func=cmd_export, tol=[], tolerances_file=None)


def _samples_command(sub: Any) -> None:
    p = sub.add_parser("samples", help="generate the built-in sample library",
                       description="Write the built-in sample STEP library into OUT.")
    p.add_argument("out", type=Path, metavar="OUT", help="output folder")
    p.set_defaults(func=cmd_samples, tol=[], tolerances_file=None)


def _workspace(p: argparse.ArgumentParser, settings: Settings) -> None:
    p.add_argument("--workspace", type=Path, default=settings.workspace,
                   help=f"workspace folder (default {settings.workspace})")


def _tolerances(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tol", action="append", default=[], metavar="NAME=VALUE",
                   help="override one tolerance (repeatable), e.g. --tol contact_mm=0.2; "
                   f"names: {', '.join(DEFAULT_TOLERANCES.as_dict())}")
    p.add_argument("--tolerances", dest="tolerances_file", type=Path, default=None,
                   metavar="FILE", help="JSON object of tolerance overrides (a run's "
                   "tolerances.json reads back); --tol applies on top")


if __name__ == "__main__":
    sys.exit(main())
