"""The configuration of each flow: one typed object per flow, grouped the way a QA team reads it.

``NightConfig`` is the nightly flow's one parameter, what ``run_stages`` reads, what the CLI's
options are made from (``flows.cli_options``) and what the deployment form shows: ``library`` (what
is checked), ``capture`` (how it is seen), ``models`` (the checkpoints, the model version),
``thresholds`` (what a pass is), ``runtime`` (where and with how much of the machine) and the run's
``tolerances``. Every field carries a description and its allowed range (the JSON schema's
``minimum``/``maximum``, repeated in the description for the form and ``--help``), and unknown keys
are refused, so a deployment parameter that does not fit fails before any work with a message naming
the field. What a schema cannot know (the library has files, the categories exist, the checkpoints
load) is checked by ``flows.preflight``.

The single-stage flows take the groups they use, in the same shape: ``IngestRun`` (the
``ingest`` flow and ``mateqa ingest``), ``CaptureRun`` (``capture``), ``ExportRun``
(``export`` and ``mateqa export``); training's is ``models.training.config.TrainConfig``. A
default lives once, in its field: the stages' own configs take the value from here
(``ScanConfig.views_per_scene`` has no default of its own).
"""

from __future__ import annotations

import math
from dataclasses import fields
from functools import cache
from typing import Annotated, Any, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from flows.settings import FileMB, FileSeconds, MemoryMB, Workers

# The paper's camera circle has 125 views; more per scene would repeat them.
Views = Annotated[int, Field(ge=1, le=125)]
# Grid sides of the occupancy written at ingest: below 8 a part is a few voxels; 256 is the
# paper's output, 0.2-2 s and about 2 MB a part.
VoxelSide = Annotated[int, Field(ge=8, le=256)]
Name = Annotated[str, Field(min_length=1)]
Count = Annotated[int, Field(ge=1, le=1000)]


def _ranges(schema: dict[str, Any]) -> None:
    """Append each property's allowed range to its description (the form shows descriptions;
    the bounds themselves stay in the schema for validators)."""
    for prop in schema.get("properties", {}).values():
        text = range_text(prop)
        if text and "description" in prop:
            prop["description"] += f" (allowed: {text})"


def range_text(prop: dict[str, Any]) -> str:
    """``1 to 125``, ``> 0``, ``8 to 256 each`` ... of a property's JSON schema; '' if none."""
    for option in prop.get("anyOf", []):
        if option.get("type") != "null":
            return range_text(option)
    if prop.get("type") == "array":
        inner = range_text(prop.get("items", {}))
        return f"{inner} each" if inner else ""
    bounds = {key: _number(prop[key]) for key in _BOUNDS if key in prop}
    if "minimum" in bounds and "maximum" in bounds:
        return f"{bounds['minimum']} to {bounds['maximum']}"
    return " and ".join(f"{_BOUNDS[key]} {value}" for key, value in bounds.items())


_BOUNDS = {"minimum": ">=", "exclusiveMinimum": ">", "maximum": "<=", "exclusiveMaximum": "<"}
_RANGE_ERRORS = {"greater_than", "greater_than_equal", "less_than", "less_than_equal"}


def _number(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


class _Group(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, json_schema_extra=_ranges)


class LibraryOptions(_Group):
    """What the night checks: the STEP library and the grids ingest writes of every part."""

    path: str | None = Field(
        default=None, description="folder of STEP files (categories are its sub-folders) or "
        "a CSV with columns path,category; null: the built-in sample library")
    categories: list[Name] | None = Field(
        default=None, min_length=1, description="only these categories of the library, each "
        "one the library has; null: every category")
    voxel_sizes: list[VoxelSide] = Field(
        default=[32, 64], min_length=1, max_length=4,
        description="occupancy grid sides written for every part, voxels")
    batch_size: Count = Field(default=12, description="files per ingest task")


class CaptureOptions(_Group):
    """How the parts are seen: rendered scenes, or recordings made elsewhere."""

    recordings: str | None = Field(
        default=None, description="folder of MCAP recordings to read instead of rendering "
        "the scenes (real logs); null: render")
    # The paper renders 125 views per object; a night over hundreds of scenes takes a handful
    # of them per scene, spread over the circle.
    views_per_scene: Views = Field(
        default=8, description="views rendered per scene, spread over the paper's 125-view "
        "circle")
    pairs_per_relation: Count = Field(
        default=4, description="scenes generated per relation (over all splits)")
    noise: bool = Field(default=False, description="switch the depth sensor noise model on")
    seed: int = Field(default=0, ge=0, le=2**32 - 1, description="seed of the scene generator")


class ModelOptions(_Group):
    """The checkpoints the learned stages use: the night's model version."""

    completion: str | None = Field(
        default=None, description="folder of completion checkpoints (*.pt); null: the shipped "
        "ones (models/checkpoints/completion)")
    relations: str | None = Field(
        default=None, description="folder of relation checkpoints (*.pt); null: the shipped "
        "ones (models/checkpoints/relations)")


class InspectionOptions(_Group):
    """How each assembly is checked as built against its design: real-size captures by the
    inspection camera, its CAD registered in the scan, each CAD mate's residuals, and planted
    defects to judge it by."""

    enabled: bool = Field(default=True, description="inspect every assembly of the library "
                          "as built (as_built.csv, the as-built verdict, the registered "
                          "relations)")
    views: int = Field(default=4, ge=1, le=16, description="inspection views around each "
                       "assembly, a full turn apart")
    distance_m: float = Field(default=0.6, ge=0.28, le=3.0, description="camera distance, "
                              "metres (a D435's working range; farther where an assembly "
                              "needs it to fit the view)")
    near_m: float = Field(default=0.3, ge=0.0, le=3.0, description="a second ring of as many "
                          "views this near, metres (the robot moving the camera in on the "
                          "assembly's middle; 0: none; a D435 measures from 0.28)")
    search_near_m: float = Field(default=0.3, ge=0.0, le=3.0, description="the intact "
                                 "capture's near ring where near_m is 0, metres, read by the "
                                 "search route alone (the registered relations; 0: none)")
    noise: bool = Field(default=True, description="the inspection camera's sensor model (a "
                        "D435: noise growing with depth, millimetre steps, holes)")
    defects: bool = Field(default=True, description="also plant defects (parts shifted 1, 2 "
                          "and 5 mm, turned 2 and 5 degrees, left out) and score what the "
                          "inspection catches")
    parts_per_defect: int = Field(default=3, ge=1, le=20, description="parts moved in each "
                                  "variant (never two sharing a mate)")
    search: bool = Field(default=True, description="register each part without the design "
                         "too (the registered relations and their F1 against the CAD's mates)")
    seed: int = Field(default=0, ge=0, le=2**32 - 1, description="seed of the planted defects")

    @field_validator("near_m", "search_near_m")
    @classmethod
    def _near(cls, value: float) -> float:
        if 0 < value < 0.28:
            raise ValueError(f"must be 0 (no near views) or 0.28 to 3 metres, got {value}")
        return value


class ThresholdOptions(_Group):
    """What a pass is: per-category thresholds and the trend against earlier nights."""

    file: str | None = Field(
        default=None, description="per-category thresholds (TOML); null: "
        "reports/thresholds.toml")
    history: int = Field(
        default=7, ge=0, le=365, description="earlier runs the trends compare with")
    fail_on_threshold: bool = Field(
        default=True, description="end the run Failed when a threshold fails or a metric "
        "regressed")


class RuntimeOptions(_Group):
    """Where the night writes and how much of the machine it may use."""

    workspace: Name = Field(default="workspace", description="the workspace folder")
    workers: Workers | None = Field(
        default=None, description="CAD worker processes per task (0: one); null: "
        "MATEQA_WORKERS")
    file_timeout_s: FileSeconds | None = Field(
        default=None, description="seconds one file may take before its worker is killed; "
        "null: MATEQA_FILE_TIMEOUT_S")
    file_memory_mb: MemoryMB | None = Field(
        default=None, description="address-space limit of each CAD worker, MB; null: "
        "MATEQA_FILE_MEMORY_MB")
    max_file_mb: FileMB | None = Field(
        default=None, description="files larger than this are skipped, MB; null: "
        "MATEQA_MAX_FILE_MB")
    dask_address: str | None = Field(
        default=None, description="a Dask scheduler (tcp://host:8786) to run the tasks on; "
        "null: MATEQA_DASK_ADDRESS; empty: this machine")


def _finite_tolerances(tol: Tolerances) -> Tolerances:
    bad = [f"{f.name}={getattr(tol, f.name)!r}" for f in fields(tol)
           if not math.isfinite(getattr(tol, f.name)) or getattr(tol, f.name) < 0]
    if bad:
        raise ValueError(f"tolerances must be finite and >= 0: {', '.join(bad)}")
    return tol


_TOLERANCES_DOC = ("every geometric tolerance of the run, finite and >= 0 (cadio/tolerances.py "
                   "gives each one's reason; written to tolerances.json)")


class NightConfig(_Group):
    """Everything a night is run with (the nightly flow's one parameter)."""

    library: LibraryOptions = Field(default=LibraryOptions(),
                                    description=LibraryOptions.__doc__)
    capture: CaptureOptions = Field(default=CaptureOptions(),
                                    description=CaptureOptions.__doc__)
    models: ModelOptions = Field(default=ModelOptions(), description=ModelOptions.__doc__)
    inspection: InspectionOptions = Field(default=InspectionOptions(),
                                          description=InspectionOptions.__doc__)
    thresholds: ThresholdOptions = Field(default=ThresholdOptions(),
                                         description=ThresholdOptions.__doc__)
    runtime: RuntimeOptions = Field(default=RuntimeOptions(),
                                    description=RuntimeOptions.__doc__)
    tolerances: Tolerances = Field(default=DEFAULT_TOLERANCES, description=_TOLERANCES_DOC)

    _finite = field_validator("tolerances")(_finite_tolerances)


# A schedule's name is its deployment's (``nightly/<name>``) and its default workspace folder.
ScheduleName = Annotated[str, Field(min_length=1, max_length=64,
                                    pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")]


class ScheduleOptions(_Group):
    """When a library's night runs: a Prefect deployment ``nightly/<name>`` on a cron."""

    name: ScheduleName = Field(
        description="the schedule's name: its deployment is nightly/<name> and its default "
        "workspace a folder of that name (letters, digits, '.', '_', '-')")
    # 02:00, as the shipped deployment: the night is done before the morning shift reads it.
    cron: str = Field(
        default="0 2 * * *", description="when the night starts: a cron of five fields "
        "(minute hour day-of-month month day-of-week) in the schedule's time zone")
    timezone: str = Field(default="UTC", description="the cron's time zone, an IANA name "
                          "(e.g. Europe/Berlin)")
    active: bool = Field(default=True, description="the schedule starts nights; off pauses it "
                         "and keeps the deployment, its workspace and its history")

    @field_validator("cron")
    @classmethod
    def _cron(cls, value: str) -> str:
        from prefect.client.schemas.schedules import CronSchedule

        try:  # Prefect's own check, as its scheduler reads the cron
            ok = len(value.split()) == 5 and bool(CronSchedule(cron=value))
        except ValueError:
            ok = False
        if not ok:
            raise ValueError("not a cron of five fields (minute hour day-of-month month "
                             "day-of-week)")
        return value

    @field_validator("timezone")
    @classmethod
    def _timezone(cls, value: str) -> str:
        from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

        try:
            ZoneInfo(value)
        except (ZoneInfoNotFoundError, ValueError):
            raise ValueError("not a time zone of the IANA database") from None
        return value


class ScheduledNight(NightConfig):
    """A schedule and the night it runs (``mateqa schedule add``): the night's configuration
    becomes the deployment's ``config`` parameter, the schedule its cron."""

    schedule: ScheduleOptions = Field(description=ScheduleOptions.__doc__)

    def night(self) -> NightConfig:
        """The night this schedule runs."""
        return NightConfig.model_validate(self.model_dump(exclude={"schedule"}))


class _StageRun(_Group):
    """The runtime and the tolerances of a single-stage flow (its groups come first)."""

    runtime: RuntimeOptions = Field(default=RuntimeOptions(),
                                    description=RuntimeOptions.__doc__)
    tolerances: Tolerances = Field(default=DEFAULT_TOLERANCES, description=_TOLERANCES_DOC)

    _finite = field_validator("tolerances")(_finite_tolerances)


class IngestRun(_StageRun):
    """Everything the ``ingest`` flow (and ``mateqa ingest``) runs with: the library read into
    the workspace's catalog, and its assemblies' mates."""

    library: LibraryOptions = Field(default=LibraryOptions(),
                                    description=LibraryOptions.__doc__)


class CaptureRun(_StageRun):
    """Everything the ``capture`` flow runs with: an ingested workspace's scenes, assemblies
    and parts captured (or its recordings read)."""

    capture: CaptureOptions = Field(default=CaptureOptions(),
                                    description=CaptureOptions.__doc__)


class ExportRun(_Group):
    """Everything the ``export`` flow (and ``mateqa export``) runs with: a finished run's
    predicted mates written back into CAD files."""

    run: Name = Field(default="latest", description="the run whose predictions to export: a "
                      "run id of the workspace, or latest")
    out: str | None = Field(default=None, description="folder for the exports; null: the "
                            "run's exports/")
    models: ModelOptions = Field(default=ModelOptions(), description="the checkpoints the run "
                                 "used, named in every export (their digests)")
    runtime: RuntimeOptions = Field(default=RuntimeOptions(),
                                    description=RuntimeOptions.__doc__)


class ConfigError(ValueError):
    """A night's configuration that cannot run: ``field`` (dotted, e.g. ``library.path``) and
    the reason, or several of them."""

    def __init__(self, problems: list[tuple[str, str]]) -> None:
        self.problems = problems
        super().__init__("; ".join(f"{f}: {r}" for f, r in problems))

    def __reduce__(self) -> tuple[type[ConfigError], tuple[list[tuple[str, str]]]]:
        return ConfigError, (self.problems,)  # pickles with its fields, as a state's data


@cache
def _schema(kind: type[BaseModel]) -> dict[str, Any]:
    return kind.model_json_schema()


def field_schema(path: str, kind: type[BaseModel] = NightConfig) -> dict[str, Any]:
    """The JSON schema of one field of a flow's configuration (dotted path), refs resolved.

    Raises:
        KeyError: no such field.
    """
    schema = _schema(kind)
    node: dict[str, Any] = schema
    for part in path.split("."):
        if "$ref" in node:
            node = schema["$defs"][node["$ref"].rsplit("/", 1)[-1]]
        node = node["properties"][part]
    return node


def config_problems(exc: ValidationError, kind: type[BaseModel] = NightConfig
                    ) -> list[tuple[str, str]]:
    """(field, reason with the allowed range and the value given) of each validation error."""
    problems = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"] if not isinstance(p, int))
        try:
            allowed = range_text(field_schema(loc, kind))
        except KeyError:  # an unknown key: no schema of its own
            allowed = ""
        reason = f"must be {allowed}" if err["type"] in _RANGE_ERRORS and allowed else err["msg"]
        if err["type"] != "missing":
            reason += f", got {err['input']!r}"
        problems.append((loc, reason))
    return problems


Config = TypeVar("Config", bound=BaseModel)


def night_config(values: dict[str, Any]) -> NightConfig:
    """The night's configuration of nested ``values`` (groups of fields, as the deployment
    takes them).

    Raises:
        ConfigError: a field out of range, of the wrong type, or unknown; each named.
    """
    return validated(NightConfig, values)


def validated(kind: type[Config], values: dict[str, Any]) -> Config:
    """A flow's configuration of nested ``values``.

    Raises:
        ConfigError: a field out of range, of the wrong type, or unknown; each named.
    """
    try:
        return kind.model_validate(values)
    except ValidationError as exc:
        raise ConfigError(config_problems(exc, kind)) from None


DEFAULT_NIGHT = NightConfig()
