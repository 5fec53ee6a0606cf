"""The command line's options, made from the flows' configurations and checked before any work.

Every option of ``nightly``, ``ingest``, ``export`` and ``train`` is made from a field of that
command's configuration (``COMMANDS``: ``NightConfig``, ``IngestRun``, ``ExportRun``,
``TrainConfig``): its type, its range and its description become the option's type, check and
help, and its default stays the field's (an option not given is not set, so the field's default
applies). A flag is the field's name with dashes unless ``flags`` renames it (the names users
know: ``--captures`` for ``capture.recordings``). So the CLI, a deployment's parameters and the
Python API cannot disagree on a knob or its default; ``tests/test_config.py`` proves it for
every field. The tolerances are the one group with options of their own (``--tol NAME=VALUE``,
``--tolerances FILE``). A value out of range is one line naming the option, its field and the
reason (exit 2).
"""

from __future__ import annotations

import argparse
import types
import typing
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cadio.camera import CIRCLE_VIEWS
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances, read_tolerances

if TYPE_CHECKING:  # pydantic is imported when a command runs, not when workers import this
    from pydantic import BaseModel
    from pydantic.fields import FieldInfo

# Fields whose flag is not their name: the options users know from before the configs.
NIGHT_FLAGS = {
    "library.path": "--library", "capture.recordings": "--captures",
    "models.completion": "--completion-models", "models.relations": "--relation-models",
    "thresholds.file": "--thresholds", "runtime.file_timeout_s": "--timeout",
    "runtime.file_memory_mb": "--memory-mb",
    # the inspection's knobs by their group's name (its noise and seed are not the capture's)
    "inspection.enabled": "--inspection",
    **{f"inspection.{name}": f"--inspection-{name.replace('_', '-')}" for name in (
        "views", "distance_m", "near_m", "search_near_m", "noise", "defects",
        "parts_per_defect", "search", "seed")},
}
# Fields a command sets from somewhere else than a flag of their own.
TOLERANCES = "tolerances"  # --tol and --tolerances


@dataclass(frozen=True)
class CommandOptions:
    """How one command's options map onto its configuration.

    config: the ``module:Class`` of the configuration (imported when the parser is built).
    flags: field -> flag, where it is not the field's name. positional: field -> metavar of a
    positional argument. skip: fields set otherwise (the tolerances; train's stage).
    """

    config: str
    flags: Mapping[str, str] = field(default_factory=dict)
    positional: Mapping[str, str] = field(default_factory=dict)
    skip: frozenset[str] = frozenset({TOLERANCES})

    def kind(self) -> type[BaseModel]:
        import importlib

        module, _, name = self.config.partition(":")
        kind: type[BaseModel] = getattr(importlib.import_module(module), name)
        return kind

    def flag(self, path: str) -> str:
        if path in self.positional:
            return self.positional[path]
        return self.flags.get(path, "--" + path.rsplit(".", 1)[-1].replace("_", "-"))


COMMANDS = {
    "nightly": CommandOptions("flows.config:NightConfig", NIGHT_FLAGS),
    # ``mateqa ingest`` and ``export`` run in their own process, without Prefect's tasks: the
    # fields of batching and of a cluster are the flows' alone (``flows.stages``).
    "ingest": CommandOptions("flows.config:IngestRun", NIGHT_FLAGS,
                             positional={"library.path": "DIR"},
                             skip=frozenset({TOLERANCES, "library.batch_size",
                                             "runtime.dask_address"})),
    "export": CommandOptions("flows.config:ExportRun", NIGHT_FLAGS,
                             skip=frozenset({"runtime.dask_address", "runtime.max_file_mb"})),
    # ``--steps``, ``--methods`` and ``--out`` of ``train STAGE`` are the stage's (``STAGED``)
    "train": CommandOptions("models.training.config:TrainConfig",
                            {"relation_inputs": "--inputs"}, skip=frozenset({"stages"})),
    # a schedule is a night's options and when it runs; ``set`` changes the fields given
    **{f"schedule {action}": CommandOptions("flows.config:ScheduledNight", NIGHT_FLAGS,
                                            positional={"schedule.name": "NAME"})
       for action in ("add", "set")},
}
# The commands whose configuration is a night's (``nightly`` runs it, ``schedule`` keeps it).
NIGHTS = ("nightly", "schedule add", "schedule set")
# train's options that mean the field of the stage given: ``train relations --steps 2000``.
STAGED = {"steps": "{stage}_steps", "methods": "{stage}_methods", "out": "{stage}_out"}


def leaf_fields(kind: type[BaseModel], prefix: str = "") -> Iterator[tuple[str, FieldInfo]]:
    """(dotted path, field) of every field of a configuration, through its groups."""
    from pydantic import BaseModel

    for name, info in kind.model_fields.items():
        path = f"{prefix}{name}"
        inner = info.annotation
        if isinstance(inner, type) and issubclass(inner, BaseModel):
            yield from leaf_fields(inner, f"{path}.")
        else:
            yield path, info


def dest(path: str) -> str:
    """The argparse destination of a field (``capture.noise`` -> ``capture__noise``)."""
    return path.replace(".", "__")


def add_config_options(parser: argparse.ArgumentParser, command: str) -> None:
    """An option (or positional) for every field of the command's configuration."""
    from flows.config import range_text

    spec = COMMANDS[command]
    kind = spec.kind()
    schema = kind.model_json_schema()
    for path, info in leaf_fields(kind):
        if path in spec.skip or path.split(".")[0] in spec.skip:
            continue
        kwargs = _argument(info)
        text = (info.description or "").rstrip(".")
        allowed = range_text(_property(schema, path))
        if allowed and "(allowed:" not in text:
            text += f" (allowed: {allowed})"
        if info.default is not None and not isinstance(info.default, bool):
            text += f" (default: {_shown(info.default)})"
        if path in spec.positional:
            parser.add_argument(dest(path), metavar=spec.positional[path], help=text, **kwargs)
        else:
            if "action" not in kwargs and "choices" not in kwargs:
                kwargs["metavar"] = path.rsplit(".", 1)[-1].upper()
            parser.add_argument(spec.flag(path), dest=dest(path), default=None, help=text,
                                **kwargs)


def _shown(value: Any) -> str:
    if isinstance(value, list | tuple):
        return " ".join(str(v) for v in value)
    return str(value)


def _property(schema: dict[str, Any], path: str) -> dict[str, Any]:
    node = schema
    for part in path.split("."):
        if "$ref" in node:
            node = schema["$defs"][node["$ref"].rsplit("/", 1)[-1]]
        node = node["properties"][part]
    return node


def _argument(info: FieldInfo) -> dict[str, Any]:
    """argparse keywords for a field's annotation: its type, how many values, choices."""
    kind = _unoptional(info.annotation)
    origin = typing.get_origin(kind)
    if kind is bool:
        return {"action": argparse.BooleanOptionalAction}
    if origin in (list, tuple):
        args = typing.get_args(kind)
        item = _scalar(args[0])
        many = {"nargs": len(args)} if origin is tuple and Ellipsis not in args else \
            {"nargs": "+"}
        return {**many, **item}
    return _scalar(kind)


def _unoptional(kind: Any) -> Any:
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        rest = [a for a in typing.get_args(kind) if a is not type(None)]
        return rest[0] if len(rest) == 1 else kind
    return kind


def _scalar(kind: Any) -> dict[str, Any]:
    kind = _unoptional(kind)
    while typing.get_origin(kind) is typing.Annotated:
        kind = typing.get_args(kind)[0]
    if typing.get_origin(kind) is typing.Literal:
        return {"choices": list(typing.get_args(kind))}
    if kind in (int, float):
        return {"type": kind}
    return {"type": str}


def config_of(args: argparse.Namespace) -> Any:
    """The configuration of the command's options (None for commands without one).

    Raises:
        ValueError: an option out of its field's range, each named with its field.
    """
    spec = COMMANDS.get(args.command)
    if spec is None:
        return None
    from flows.config import ConfigError, validated

    values: dict[str, Any] = {}
    for path, _ in leaf_fields(spec.kind()):
        if path in spec.skip:  # set from other options (``_extra``)
            continue
        value = getattr(args, dest(path), None)
        if value is not None:
            _put(values, path, str(value) if isinstance(value, Path) else value)
    for path, value in _extra(args).items():
        _put(values, path, value)
    try:
        return validated(spec.kind(), values)
    except ConfigError as exc:
        raise ValueError("; ".join(f"{option_of(field, args.command)}: {reason}"
                                   for field, reason in exc.problems)) from None


def _extra(args: argparse.Namespace) -> dict[str, Any]:
    """The fields a command sets from other options: the tolerances, train's stage and its
    stage's options, and a night's workers (0: one per task, which already run side by
    side)."""
    out: dict[str, Any] = {}
    if args.command in ("nightly", "ingest") or (
            args.command in NIGHTS and (args.tol or args.tolerances_file)):
        out[TOLERANCES] = args.tolerances  # a schedule keeps only tolerances it was given
    if args.command in NIGHTS and getattr(args, dest("runtime.workers"), None) == 0:
        out["runtime.workers"] = 1
    if args.command == "train":
        out["stages"] = [args.stage]
        stage = "completion" if args.stage == "completion" else "relation"
        for option, field_name in STAGED.items():
            if getattr(args, option, None) is not None:
                value = getattr(args, option)
                out[field_name.format(stage=stage)] = str(value) if isinstance(
                    value, Path) else value
    return out


def _put(values: dict[str, Any], path: str, value: Any) -> None:
    *groups, name = path.split(".")
    node = values
    for group in groups:
        node = node.setdefault(group, {})
    node[name] = value


def option_of(field: str, command: str) -> str:
    """``--views-per-scene (capture.views_per_scene)``: the option that sets a field."""
    spec = COMMANDS.get(command)
    if spec is None or field == TOLERANCES:
        return field
    return f"{spec.flag(field)} ({field})"


def bounded(kind: Callable[[str], Any], low: float, high: float) -> Callable[[str], Any]:
    """An argparse type: ``kind`` within [low, high] (for options that are no config's field)."""
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
    config = args.config
    workspace = _workspace(args)
    if workspace is not None and args.command != "export":
        check_workspace(workspace, _workspace_option(args.command), problems)
    if workspace is not None and args.command in ("ingest", "mates", "capture") and \
            not problems:  # a night's: below
        check_own_workspace(workspace, _workspace_option(args.command), problems)
    out = _out(args)
    if out is not None:
        check_workspace(out, "OUT" if args.command == "samples" else "--out", problems)
    _arguments(args, problems)
    if args.command == "export":
        found: list[tuple[str, str]] = []
        check_finished_run(config.runtime.workspace, config.run, found)
        problems += [(f"--{where}", reason) for where, reason in found]
    warnings: list[str] = []
    if args.command == "nightly" and not problems:
        try:
            warnings = check_night(config)
        except ConfigError as exc:
            problems += [(option_of(field, "nightly"), reason) for field, reason in exc.problems]
    if problems:
        raise ValueError("; ".join(f"{where}: {reason}" for where, reason in problems))
    return warnings


def _arguments(args: argparse.Namespace, problems: list[tuple[str, str]]) -> None:
    """A command's own arguments: the files it reads, the views it renders."""
    if args.command == "mates":
        _regular_file(args.step, "STEP", problems)
    if args.command == "inspect":
        _regular_file(args.step, "ASSEMBLY.step", problems)
        _regular_file(args.recording, "RECORDING.mcap", problems)
    if args.command == "capture" and not 1 <= args.views <= CIRCLE_VIEWS:
        problems.append(("--views", f"must be 1 to {CIRCLE_VIEWS}, got {args.views}"))


def _workspace(args: argparse.Namespace) -> str | Path | None:
    if args.command in ("nightly", "ingest", "export"):
        return str(args.config.runtime.workspace)
    if args.command == "train":
        return str(args.config.workspace)
    return getattr(args, "workspace", None)


def _workspace_option(command: str) -> str:
    return option_of("runtime.workspace", command) if command in ("nightly", "ingest") else \
        "--workspace"


def _out(args: argparse.Namespace) -> str | Path | None:
    if args.command == "export":
        out: str | None = args.config.out
        return out
    if args.command in ("train", "inspect"):
        return None  # the stage's out is checked where it is written; inspect's is a file
    return getattr(args, "out", None)


def _regular_file(path: Path, where: str, problems: list[tuple[str, str]]) -> None:
    if not path.exists():
        problems.append((where, f"{path} does not exist"))
    elif not path.is_file():
        problems.append((where, f"{path} is not a file"))
