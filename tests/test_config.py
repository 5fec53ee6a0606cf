"""The flows' configurations: every field described with its range, each flow's one
parameter, the CLI's options made from them (and their defaults the fields'), and a bad value
named by its field."""

from __future__ import annotations

import argparse
import inspect
from typing import Any

import pytest

from cadio.tolerances import DEFAULT_TOLERANCES
from flows.cli import _parser
from flows.cli_options import COMMANDS, dest, leaf_fields
from flows.config import (
    DEFAULT_NIGHT,
    ConfigError,
    NightConfig,
    field_schema,
    night_config,
    range_text,
)

GROUPS = ("library", "capture", "models", "inspection", "thresholds", "runtime")


def _leaves() -> list[str]:
    """Every field of the groups, dotted."""
    return [f"{group}.{name}" for group in GROUPS
            for name in type(getattr(DEFAULT_NIGHT, group)).model_fields]


def test_every_field_has_a_description_and_each_bounded_one_its_range() -> None:
    assert tuple(NightConfig.model_fields) == (*GROUPS, "tolerances")
    for path in _leaves():
        schema = field_schema(path)
        assert len(schema.get("description", "")) > 15, path
        if range_text(schema):
            assert f"(allowed: {range_text(schema)})" in schema["description"], path
    assert field_schema("capture.views_per_scene")["description"].endswith(
        "(allowed: 1 to 125)")


def test_the_flows_take_the_one_object() -> None:
    from flows.nightly import nightly, run_stages

    for flow in (nightly, run_stages):
        params = inspect.signature(flow.fn).parameters
        assert list(params) == ["config"]
    assert inspect.signature(nightly.fn).parameters["config"].default == NightConfig()


@pytest.mark.parametrize(("values", "field", "reason"), [
    ({"capture": {"views_per_scene": 0}}, "capture.views_per_scene", "must be 1 to 125, got 0"),
    ({"runtime": {"file_memory_mb": 1}}, "runtime.file_memory_mb", "must be 2048 to"),
    ({"library": {"voxel_sizes": [32, 4]}}, "library.voxel_sizes", "8 to 256 each, got 4"),
    ({"library": {"categories": [""]}}, "library.categories", "at least 1 character"),
    ({"capture": {"views": 2}}, "capture.views", "Extra inputs are not permitted"),
    ({"tolerances": {"contact_mm": -1}}, "tolerances", "contact_mm=-1"),
    ({"thresholds": {"history": "a week"}}, "thresholds.history", "valid integer"),
    ({"inspection": {"near_m": 0.1}}, "inspection.near_m", "0 (no near views) or 0.28 to 3"),
])
def test_a_bad_value_is_named_by_its_field(values: dict[str, Any], field: str,
                                           reason: str) -> None:
    with pytest.raises(ConfigError) as caught:
        night_config(values)
    [(named, said)] = caught.value.problems
    assert named == field and reason in said, said


def test_a_config_round_trips_through_json_as_a_deployment_passes_it() -> None:
    config = night_config({"library": {"path": "/data/step", "categories": ["fasteners"]},
                           "capture": {"views_per_scene": 3},
                           "tolerances": {**DEFAULT_TOLERANCES.as_dict(), "contact_mm": 0.2}})
    again = night_config(config.model_dump(mode="json"))
    assert again == config and again.tolerances.contact_mm == 0.2


def _subparser(command: str) -> argparse.ArgumentParser:
    """The parser of a command (``schedule add``: of an action of a command)."""
    parser = _parser()
    for word in command.split():
        sub = next(a for a in parser._subparsers._group_actions  # type: ignore[union-attr]
                   if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[word]
    return parser


# The least each command needs on its command line (positionals).
REQUIRED = {"nightly": [], "ingest": ["lib"], "export": [], "train": ["completion"],
            "schedule add": ["lib"], "schedule set": ["lib"]}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_field_of_a_command_s_config_is_one_of_its_options(command: str) -> None:
    spec = COMMANDS[command]
    dests = {a.dest: a for a in _subparser(command)._actions}
    for path, info in leaf_fields(spec.kind()):
        if path in spec.skip:
            assert dest(path) not in dests, path
            continue
        action = dests[dest(path)]
        assert (info.description or "").split(";")[0] in (action.help or ""), path
        if info.default is not None and not isinstance(info.default, bool) and \
                not action.option_strings == []:
            assert "(default: " in (action.help or ""), path


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_no_option_given_leaves_every_field_at_its_config_s_default(command: str) -> None:
    from flows.cli_options import config_of, tolerances_of

    args = _parser().parse_args([*command.split(), *REQUIRED[command]])
    args.tolerances = tolerances_of(args)
    config = config_of(args)
    kind = COMMANDS[command].kind()
    given = {"nightly": {}, "ingest": {"library": {"path": "lib"}}, "export": {},
             "train": {"stages": ["completion"]}, "schedule add": {"schedule": {"name": "lib"}},
             "schedule set": {"schedule": {"name": "lib"}}}[command]
    assert config == kind.model_validate(given)


def test_an_option_sets_its_field_and_a_bad_one_names_it() -> None:
    from flows.cli_options import config_of, tolerances_of

    args = _parser().parse_args(["nightly", "--views-per-scene", "3", "--captures", "/rec",
                                 "--no-fail-on-threshold", "--noise", "--timeout", "60"])
    args.tolerances = tolerances_of(args)
    night = config_of(args)
    assert (night.capture.views_per_scene, night.capture.recordings, night.capture.noise,
            night.thresholds.fail_on_threshold, night.runtime.file_timeout_s) == (
        3, "/rec", True, False, 60.0)
    args = _parser().parse_args(["nightly", "--views-per-scene", "300"])
    args.tolerances = tolerances_of(args)
    with pytest.raises(ValueError, match=r"--views-per-scene \(capture.views_per_scene\): "
                                         r"must be 1 to 125, got 300"):
        config_of(args)
    args = _parser().parse_args(["train", "relations", "--steps", "300", "--inputs", "truth"])
    args.tolerances = tolerances_of(args)
    train = config_of(args)
    assert (train.stages, train.relation_steps, train.completion_steps,
            train.relation_inputs) == (["relations"], 300, 2000, ["truth"])


def test_every_flow_takes_its_one_config() -> None:
    from flows.stages import capture, export, ingest
    from flows.train import train

    for flow, kind in ((ingest, "IngestRun"), (capture, "CaptureRun"), (export, "ExportRun"),
                       (train, "TrainConfig")):
        params = inspect.signature(flow.fn).parameters
        assert list(params) == ["config"], flow.name
        assert type(params["config"].default).__name__ == kind
