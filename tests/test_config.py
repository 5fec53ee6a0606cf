"""The night's one configuration: every field described with its range, the flow's one
parameter, the CLI's options mapped onto it, and a bad value named by its field."""

from __future__ import annotations

import argparse
import inspect
from typing import Any

import pytest

from cadio.tolerances import DEFAULT_TOLERANCES
from flows.cli import _parser
from flows.cli_options import OPTION_FIELDS
from flows.config import (
    DEFAULT_NIGHT,
    ConfigError,
    NightConfig,
    field_schema,
    night_config,
    range_text,
)

GROUPS = ("library", "capture", "models", "thresholds", "runtime")


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


def test_every_field_is_an_option_of_nightly() -> None:
    nightly = next(a for a in _parser()._subparsers._group_actions  # type: ignore[union-attr]
                   if isinstance(a, argparse._SubParsersAction)).choices["nightly"]
    dests = {a.dest for a in nightly._actions}
    mapped = {OPTION_FIELDS[d] for d in dests if d in OPTION_FIELDS}
    assert mapped == set(_leaves())
    for field in OPTION_FIELDS.values():
        field_schema(field)  # each maps onto a real field
