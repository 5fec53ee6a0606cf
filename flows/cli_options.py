"""The command line's options checked before any work: each maps onto a field of the night's
configuration (``flows.config.NightConfig``) and is held to that field's range; the settings
files (``--tolerances``, ``--thresholds``, a library CSV) are read; folders named by options
must be folders. A problem is one line naming the option, the field and the reason (exit 2).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances, read_tolerances

if TYPE_CHECKING:  # pydantic is imported when a command runs, not when workers import this
    from flows.config import NightConfig

# Option (argparse dest) -> the field of NightConfig it sets.
OPTION_FIELDS = {
    "library": "library.path", "categories": "library.categories",
    "voxel_sizes": "library.voxel_sizes",
    "captures": "capture.recordings", "views_per_scene": "capture.views_per_scene",
    "views": "capture.views_per_scene", "pairs_per_relation": "capture.pairs_per_relation",
    "noise": "capture.noise", "seed": "capture.seed", "batch_size": "library.batch_size",
    "completion_models": "models.completion", "relation_models": "models.relations",
    "thresholds": "thresholds.file", "history": "thresholds.history",
    "fail_on_threshold": "thresholds.fail_on_threshold",
    "workspace": "runtime.workspace", "workers": "runtime.workers",
    "timeout": "runtime.file_timeout_s", "memory_mb": "runtime.file_memory_mb",
    "max_file_mb": "runtime.max_file_mb", "dask_address": "runtime.dask_address",
}
# Commands whose options are their own (training knobs), not a night's: train's --seed and
# --pairs-per-relation are the corpus's.
_OWN_OPTIONS = {"train", "ship", "serve", "samples"}


def allowed(field: str) -> str:
    """`` (allowed: 1 to 125)`` for an option's help, from its field's schema."""
    from flows.config import field_schema, range_text

    text = range_text(field_schema(field))
    return f" (allowed: {text})" if text else ""


def bounded(kind: Callable[[str], Any], low: float, high: float) -> Callable[[str], Any]:
    """An argparse type: ``kind`` within [low, high] (for options that are no night's field)."""
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be {low:g} to {high:g}, got {text}")
        return value
    return parse


def tolerances_of(args: argparse.Namespace) -> Tolerances:
    """The run's tolerances: the defaults, then ``--tolerances FILE``, then each ``--tol``.

    Raises:
        ValueError: an unreadable file, an unknown name, a value that is no finite number >= 0.
    """
    tol = read_tolerances(args.tolerances_file) if args.tolerances_file else DEFAULT_TOLERANCES
    overrides = {}
    for item in args.tol:
        name, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--tol takes NAME=VALUE, got {item!r}")
        overrides[name.strip()] = value.strip()
    return tol.with_overrides(overrides)


def config_of(args: argparse.Namespace) -> NightConfig | None:
    """The ``NightConfig`` of the command's options (None for commands with their own).

    Raises:
        ValueError: an option out of its field's range, each named with its field.
    """
    if args.command in _OWN_OPTIONS:
        return None
    from flows.config import ConfigError, night_config

    values: dict[str, dict[str, Any]] = {}
    for dest, field in OPTION_FIELDS.items():
        value = getattr(args, dest, None)
        if value is not None:
            group, name = field.split(".")
            values.setdefault(group, {})[name] = str(value) if isinstance(value, Path) else value
    if args.command == "nightly" and getattr(args, "workers", None) == 0:
        values["runtime"]["workers"] = 1  # the flow's tasks already run side by side
    try:
        return night_config({**values, "tolerances": args.tolerances})
    except ConfigError as exc:
        raise ValueError("; ".join(f"{_option(field, args)}: {reason}"
                                   for field, reason in exc.problems)) from None


def _option(field: str, args: argparse.Namespace) -> str:
    """``--views-per-scene (capture.views_per_scene)``: the option that set a field."""
    for dest, mapped in OPTION_FIELDS.items():
        if mapped == field and hasattr(args, dest):
            flag = "DIR" if (args.command, dest) == ("ingest", "library") else \
                "--" + dest.replace("_", "-")
            return f"{flag} ({field})"
    return field


def check_inputs(args: argparse.Namespace) -> list[str]:
    """The folders and files the options name: a workspace or output that is a file, a STEP
    argument that is missing or a folder, a run that does not exist or did not complete; for
    ``nightly``, everything ``flows.preflight.check_night`` checks. Returns its warnings.

    Raises:
        ValueError: every problem, each naming the option and the path.
    """
    from flows.config import ConfigError
    from flows.preflight import (
        check_finished_run,
        check_night,
        check_own_workspace,
        check_workspace,
    )

    problems: list[tuple[str, str]] = []
    if hasattr(args, "workspace") and args.command != "export":
        check_workspace(args.workspace, "--workspace", problems)
    if args.command in ("ingest", "mates", "capture") and not problems:  # a night's: below
        check_own_workspace(args.workspace, "--workspace", problems)
    if getattr(args, "out", None) is not None:
        check_workspace(args.out, "OUT" if args.command == "samples" else "--out", problems)
    if args.command == "mates":
        _regular_file(args.step, "STEP", problems)
    if args.command == "export":
        found: list[tuple[str, str]] = []
        check_finished_run(args.workspace, args.run, found)
        problems += [(f"--{where}", reason) for where, reason in found]
    warnings: list[str] = []
    if args.command == "nightly" and not problems:
        try:
            warnings = check_night(args.config)
        except ConfigError as exc:
            problems += [(_option(field, args), reason) for field, reason in exc.problems]
    if problems:
        raise ValueError("; ".join(f"{where}: {reason}" for where, reason in problems))
    return warnings


def _regular_file(path: Path, where: str, problems: list[tuple[str, str]]) -> None:
    if not path.exists():
        problems.append((where, f"{path} does not exist"))
    elif not path.is_file():
        problems.append((where, f"{path} is not a file"))
