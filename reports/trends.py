"""The nightly's headline metrics per category, checked against thresholds and earlier runs.

``run_metrics`` reads one run folder into a long table (category, metric, value, n);
``check_metrics`` puts the previous run's value, the mean of the last runs, the threshold and a
status beside each value (``categories.csv``); ``write_junit`` turns the checks into JUnit XML
so that any CI system shows them. Pure pandas and the standard library: no CAD, no torch.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from cadio.errors import InputFileError
from cadio.inputs import read_text
from cadio.workspace import atomic_write
from reports.methods import completion_ours, product

DEFAULT_THRESHOLDS = Path(__file__).with_name("thresholds.toml")
CATEGORIES_COLUMNS = ("category", "metric", "value", "previous", "threshold", "status",
                      "direction", "max_drop", "mean_last_n", "n", "resampled")
STATUSES = ("pass", "fail", "regressed", "no-threshold", "no-data", "too-few")
ALL = "all"


@dataclass(frozen=True)
class Limit:
    """One metric's threshold: ``floor`` (worst acceptable value) and ``max_drop`` (largest
    allowed worsening against the previous run); None where not set."""

    floor: float | None = None
    max_drop: float | None = None


@dataclass(frozen=True)
class Thresholds:
    """Per metric a default ``Limit`` and per-category overrides."""

    limits: Mapping[str, Limit] = field(default_factory=dict)
    categories: Mapping[str, Mapping[str, Limit]] = field(default_factory=dict)
    source: str = ""
    # Fewer parts, pairs or files than this and a value is reported but not checked
    # ("too-few"): a mean over a handful says little about a category.
    min_n: int = 10
    # The run the floors were calibrated from (``reports.calibrate``); empty for floors set by
    # hand, as the shipped ones are.
    reference_run: str = ""

    def limit(self, metric: str, category: str) -> Limit:
        base = self.limits.get(metric, Limit())
        over = self.categories.get(metric, {}).get(category)
        if over is None:
            return base
        return Limit(base.floor if over.floor is None else over.floor,
                     base.max_drop if over.max_drop is None else over.max_drop)


class ThresholdsError(ValueError):
    """A thresholds file that cannot be used; the message names the file and the reason."""

    def __init__(self, path: Path, reason: str) -> None:
        super().__init__(f"{path}: {reason}")


def read_thresholds(path: Path) -> Thresholds:
    """The thresholds of a TOML file (see ``reports/thresholds.toml`` for the format).

    Raises:
        ThresholdsError: unreadable TOML, an unknown metric or key (a typo would otherwise
            switch a check off without a word), a table where a number belongs or the other
            way round, or a limit that is not a finite number (``max_drop`` >= 0).
    """
    try:
        data = tomllib.loads(read_text(path, "thresholds file", max_bytes=1 << 20))
    except InputFileError as exc:
        raise ThresholdsError(path, exc.reason) from None
    except tomllib.TOMLDecodeError as exc:
        raise ThresholdsError(path, f"cannot read thresholds: {exc}") from exc
    limits, categories = {}, {}
    min_n = data.pop("min_n", Thresholds.min_n)
    if isinstance(min_n, bool) or not isinstance(min_n, int) or min_n < 0:
        raise ThresholdsError(path, f"min_n must be a count, got {min_n!r}")
    reference = data.pop("reference_run", "")
    if not isinstance(reference, str):
        raise ThresholdsError(path, f"reference_run must be a run folder's path, got "
                              f"{reference!r}")
    for metric, table in data.items():
        if metric not in METRICS:
            raise ThresholdsError(path, f"unknown metric {metric!r} (known: {sorted(METRICS)})")
        if not isinstance(table, dict):
            raise ThresholdsError(path, f"[{metric}] must be a table, got {table!r}")
        limits[metric] = _limit(path, metric, table, (*_LIMIT_KEYS, "categories"))
        over = table.get("categories", {})
        if not isinstance(over, dict):
            raise ThresholdsError(path, f"{metric}.categories must be a table of categories, "
                                  f"got {over!r}")
        categories[metric] = {c: _limit(path, f"{metric}.categories.{c}", t, _LIMIT_KEYS)
                              for c, t in over.items()}
    return Thresholds(limits, categories, str(path), min_n, reference)


_LIMIT_KEYS = ("floor", "max_drop")


def _limit(path: Path, where: str, table: object, known: tuple[str, ...]) -> Limit:
    if not isinstance(table, dict):
        raise ThresholdsError(path, f"[{where}] must be a table of {' and '.join(_LIMIT_KEYS)}, "
                              f"got {table!r}")
    unknown = sorted(set(table) - set(known))
    if unknown:
        raise ThresholdsError(path, f"[{where}] has unknown key(s) {unknown} (known: "
                              f"{', '.join(known)})")
    values = {}
    for key in _LIMIT_KEYS:
        value = table.get(key)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int | float)
                                  or not math.isfinite(value)):
            raise ThresholdsError(path, f"{where}.{key} must be a finite number, got {value!r}")
        if key == "max_drop" and value is not None and value < 0:
            raise ThresholdsError(path, f"{where}.max_drop must be >= 0, got {value!r}")
        values[key] = None if value is None else float(value)
    return Limit(**values)


# ---------------------------------------------------------------- metrics of one run


def _read_csv(path: Path) -> pd.DataFrame:
    return pd.read_csv(path) if path.is_file() and path.stat().st_size else pd.DataFrame()


def _ingest_ok(run: Path) -> pd.DataFrame:
    path = run / "ingest.json"
    if not path.is_file():
        return pd.DataFrame()
    data = json.loads(path.read_text())
    rows = [*data.get("per_category", []), {**data.get("totals", {}), "category": ALL}]
    return pd.DataFrame([{"category": r["category"], "value": r["ok"] / r["files"],
                          "n": r["files"]} for r in rows if r.get("files")])


def _completion(metric: str) -> Callable[[Path], pd.DataFrame]:
    def read(run: Path) -> pd.DataFrame:
        table = _read_csv(run / "completion_categories.csv")
        if table.empty:
            return table
        method, protocol = completion_ours()
        rows = table[(table["method"] == method) & (table["protocol"] == protocol)]
        return rows.rename(columns={metric: "value", "n_parts": "n"})[["category", "value", "n"]]
    return read


def _completion_shapes(run: Path) -> pd.DataFrame:
    """The completion headline (``reports.headline``): per distinct shape, parts scored where
    they were placed; n counts the shapes."""
    from reports.headline import read_headline

    table = read_headline(run)
    method, protocol = completion_ours()
    rows = table[(table["method"] == method) & (table["protocol"] == protocol)]
    return rows.rename(columns={"iou": "value", "n_shapes": "n"})[["category", "value", "n"]]


def _relation_accuracy(run: Path) -> pd.DataFrame:
    table = _read_csv(run / "relations_summary.csv")
    if table.empty:
        return table
    given, method = product()
    rows = table[(table["input"] == given) & (table["method"] == method)]
    return rows.groupby("category", as_index=False).agg(value=("accuracy", "mean"),
                                                        n=("n", "max"))


def _mates_f1(run: Path) -> pd.DataFrame:
    table = _read_csv(run / "assembly_mates.csv")
    if table.empty:
        return table
    rows = table[table["assembly"] == ALL]
    return pd.DataFrame([{"category": ALL, "value": rows["f1"].mean(), "n": rows["n_cad"].sum()}])


def _mate_f1(relation: str) -> Callable[[Path], pd.DataFrame]:
    """The F1 of one relation against the CAD's mates over every assembly; n counts the
    CAD's true pair views, as ``mates_f1``'s."""
    def read(run: Path) -> pd.DataFrame:
        table = _read_csv(run / "assembly_mates.csv")
        if table.empty:
            return table
        rows = table[(table["assembly"] == ALL) & (table["relation"] == relation)]
        return pd.DataFrame({"category": ALL, "value": rows["f1"].astype(float),
                             "n": rows["n_cad"]})
    return read


def _joint_agreement(run: Path) -> pd.DataFrame:
    table = _read_csv(run / "assembly_joints.csv")
    if table.empty:
        return table
    return pd.DataFrame([{"category": ALL, "value": table["agree"].mean(), "n": len(table)}])


# metric -> (reader of a run folder, higher is better)
METRICS: dict[str, tuple[Callable[[Path], pd.DataFrame], bool]] = {
    "ingest_ok_fraction": (_ingest_ok, True),
    "completion_iou_shapes": (_completion_shapes, True),
    "completion_iou": (_completion("iou"), True),
    "completion_overlap_xy": (_completion("overlap_xy"), True),
    "completion_overlap_yz": (_completion("overlap_yz"), True),
    "completion_overlap_zx": (_completion("overlap_zx"), True),
    "completion_chamfer_l1": (_completion("chamfer_l1"), False),
    "completion_fscore": (_completion("fscore"), True),
    "relation_accuracy": (_relation_accuracy, True),
    "mates_f1": (_mates_f1, True),
    "mates_f1_concentric": (_mate_f1("concentric"), True),
    "mates_f1_coincident": (_mate_f1("coincident"), True),
    "joint_agreement": (_joint_agreement, True),
}


# Metrics whose values lie in [0, 1]: a mean of n such values varies from sample to sample by
# at most sqrt(v (1 - v) / n) (the variance of a [0, 1] variable of mean v is at most that).
BOUNDED = frozenset(m for m in METRICS if m != "completion_chamfer_l1")
RELATION_METRICS = ("relation_accuracy",)
COMPLETION_METRICS = tuple(m for m in METRICS if m.startswith("completion_"))


def run_metrics(run: Path) -> pd.DataFrame:
    """Every metric of a run folder: columns category, metric, value, n (absent: no row) and
    sample (what the value was measured on, where the run says: ``run_samples``; else None)."""
    frames = [reader(run).assign(metric=name) for name, (reader, _) in METRICS.items()]
    frames = [f for f in frames if len(f)]
    if not frames:
        return pd.DataFrame(columns=["category", "metric", "value", "n", "sample"])
    table = pd.concat(frames, ignore_index=True)[["category", "metric", "value", "n"]]
    samples = run_samples(run)
    table["sample"] = [samples.get((c, m)) for c, m in zip(table["category"], table["metric"],
                                                           strict=True)]
    return table.astype({"category": "str", "metric": "str", "value": "float64"})


Sample = frozenset[tuple[str, ...]]


def run_samples(run: Path) -> dict[tuple[str, str], Sample]:
    """Per category and metric, what a run measured it on: the pair views of the relations
    (scene, view, parts), the parts, contexts and views of the completions. Two nights on one
    sample differ only where the code or the models did; a library that grew draws some other
    pair scenes and scores its new parts, and a small category's figure moves by that alone."""
    out: dict[tuple[str, str], Sample] = {}
    pairs = _read_parquet(run / "relations_pairs.parquet")
    if not pairs.empty:
        given, method = product()
        rows = pairs[(pairs["input"] == given) & (pairs["method"] == method)]
        for category, sample in _samples(rows, ["scene", "view", "part_a", "part_b"]).items():
            out |= {(category, m): sample for m in RELATION_METRICS}
    parts = _read_parquet(run / "completion_parts.parquet")
    if not parts.empty:
        method, protocol = completion_ours()
        rows = parts[(parts["method"] == method) & (parts["protocol"] == protocol)]
        for category, sample in _samples(rows, ["part_id", "context", "n_views",
                                                "view_deg"]).items():
            out |= {(category, m): sample for m in COMPLETION_METRICS}
    return out


def _read_parquet(path: Path) -> pd.DataFrame:
    return pd.read_parquet(path) if path.is_file() else pd.DataFrame()


def _samples(rows: pd.DataFrame, keys: list[str]) -> dict[str, Sample]:
    """Per category (and ``all``), the distinct ``keys`` of its rows."""
    def sample(frame: pd.DataFrame) -> Sample:
        return frozenset(frame[keys].astype(str).itertuples(index=False, name=None))
    out = {str(c): sample(g) for c, g in rows.groupby("category")}
    out[ALL] = sample(rows)
    return out


def changed_share(now: Sample | None, before: Sample | None) -> float:
    """The share of either night's sample the other's lacks, the larger (0: the same sample;
    NaN where either night does not say)."""
    if not now or not before:
        return math.nan
    return max(len(now - before) / len(now), len(before - now) / len(before))


# ---------------------------------------------------------------- checks and trends


def check_metrics(current: pd.DataFrame, history: Sequence[pd.DataFrame],
                  thresholds: Thresholds) -> pd.DataFrame:
    """``categories.csv``: each metric of ``current`` with the previous run's value (the last
    of ``history``, oldest first), the mean over ``history``, the threshold and the status.

    A metric a category had in the previous run but lacks now gets a row with status
    ``no-data`` (so a vanished category shows up).
    """
    previous = _by_key(history[-1]) if history else {}
    means = _means(history)
    keys = list(dict.fromkeys([*_by_key(current), *previous]))
    values = _by_key(current)
    counts = _column(current, "n")
    samples = _column(current, "sample")
    before_samples = _column(history[-1], "sample") if history else {}
    before_counts = _column(history[-1], "n") if history else {}
    rows = []
    for category, metric in keys:
        key = (category, metric)
        limit = thresholds.limit(metric, category)
        value, before = values.get(key, math.nan), previous.get(key, math.nan)
        higher = METRICS[metric][1]
        changed = changed_share(samples.get(key), before_samples.get(key))
        if changed > 0 and limit.max_drop is not None:
            limit = Limit(limit.floor, limit.max_drop + _spread(
                metric, before, changed, int(counts.get(key, 0)),
                int(before_counts.get(key, 0))))
        rows.append({"category": category, "metric": metric, "value": value,
                     "previous": before, "threshold": _nan(limit.floor),
                     "status": _status(value, before, limit, higher,
                                       int(counts.get(key, 0)) >= thresholds.min_n),
                     "direction": "higher" if higher else "lower",
                     "max_drop": _nan(limit.max_drop),
                     "mean_last_n": means.get(key, math.nan),
                     "n": int(counts.get(key, 0)), "resampled": changed})
    frame = pd.DataFrame(rows, columns=list(CATEGORIES_COLUMNS))
    order = {m: i for i, m in enumerate(METRICS)}
    frame = frame.assign(_c=frame["category"] == ALL, _m=frame["metric"].map(order))
    return frame.sort_values(["_m", "_c", "category"]).drop(columns=["_c", "_m"]).reset_index(
        drop=True)


def _by_key(table: pd.DataFrame) -> dict[tuple[str, str], float]:
    return {(r.category, r.metric): float(r.value) for r in table.itertuples()}


def _column(table: pd.DataFrame, column: str) -> dict[tuple[str, str], Any]:
    if column not in table.columns:
        return {}
    return {(str(c), str(m)): v for c, m, v in zip(table["category"], table["metric"],
                                                   table[column], strict=True)
            if not (isinstance(v, float) and math.isnan(v))}


def _spread(metric: str, previous: float, changed: float, n: int, n_before: int) -> float:
    """How far a [0, 1] mean can move by the draw alone when ``changed`` of its sample was
    drawn anew: twice the largest standard error of the difference of the two means over n
    and ``n_before`` values, of which only the changed share differs (about a 95% bound);
    unbounded where the metric is not in [0, 1] or a count is unknown: a figure on another
    sample is then held to its floor only."""
    if metric not in BOUNDED or n <= 0 or n_before <= 0 or math.isnan(previous):
        return math.inf
    v = min(max(previous, 0.0), 1.0)
    # (and never more than the changed share: values in [0, 1] move a mean no further)
    return min(changed, 2.0 * math.sqrt(v * (1 - v) * changed * (1 / n + 1 / n_before)))


def _means(history: Sequence[pd.DataFrame]) -> dict[tuple[str, str], float]:
    if not history:
        return {}
    stacked = pd.concat(history, ignore_index=True)
    return {(c, m): float(v) for (c, m), v in stacked.groupby(["category", "metric"])["value"]
            .mean().items()}


def _nan(value: float | None) -> float:
    return math.nan if value is None else value


def _status(value: float, previous: float, limit: Limit, higher: bool, enough: bool) -> str:
    if math.isnan(value):
        return "no-data"
    if not enough:
        return "too-few"
    if limit.floor is None and limit.max_drop is None:
        return "no-threshold"
    sign = 1.0 if higher else -1.0
    if limit.floor is not None and sign * (value - limit.floor) < 0:
        return "fail"
    if limit.max_drop is not None and not math.isnan(previous) and \
            sign * (previous - value) > limit.max_drop:
        return "regressed"
    return "pass"


def failed_checks(checks: pd.DataFrame) -> list[str]:
    """One line per failed or regressed check: category, metric, value, threshold, previous."""
    bad = checks[checks["status"].isin(["fail", "regressed"])]
    return [f"{r.category} {r.metric} {r.status}: {r.value:.4g} (threshold {r.threshold:.4g}, "
            f"previous {r.previous:.4g})" for r in bad.itertuples()]


def write_categories(path: Path, checks: pd.DataFrame) -> Path:
    """``categories.csv``, atomically."""
    with atomic_write(path, "w") as fh:
        checks.to_csv(fh, index=False)
    return path


# Characters XML 1.0 cannot hold, even escaped (control characters, surrogates, U+FFFE/F).
_NOT_XML = re.compile("[^\t\n\r\x20-\ud7ff\ue000-\ufffd\U00010000-\U0010ffff]")


def xml_safe(value: object) -> str:
    """``str(value)`` with what XML cannot hold written as its Python escape (``\\x1b``):
    a category is a folder name, which may hold any character but ``/``."""
    return _NOT_XML.sub(lambda m: ascii(m.group())[1:-1], str(value))


def write_junit(path: Path, checks: pd.DataFrame, suite: str,
                more: Sequence[ET.Element] = ()) -> Path:
    """JUnit XML: one test case per category (class) and metric (name); ``fail`` and
    ``regressed`` are failures, ``no-data``, ``no-threshold`` and ``too-few`` are skipped.
    ``more``: further test suites (each assembly's mates as built)."""
    failures = int(checks["status"].isin(["fail", "regressed"]).sum())
    skipped = int(checks["status"].isin(["no-data", "no-threshold", "too-few"]).sum())
    total = {k: sum(int(m.get(k, "0")) for m in more) for k in ("tests", "failures", "skipped")}
    root = ET.Element("testsuites", name="mateqa", tests=str(len(checks) + total["tests"]),
                      failures=str(failures + total["failures"]),
                      skipped=str(skipped + total["skipped"]))
    node = ET.SubElement(root, "testsuite", name=xml_safe(suite), tests=str(len(checks)),
                         failures=str(failures), errors="0", skipped=str(skipped))
    root.extend(more)
    for r in checks.itertuples():
        case = ET.SubElement(node, "testcase", classname=xml_safe(r.category),
                             name=xml_safe(r.metric))
        message = (f"{r.metric} = {r.value:.4g} ({r.direction} is better), threshold "
                   f"{r.threshold:.4g}, max drop {r.max_drop:.4g}, previous {r.previous:.4g}")
        if r.status in ("fail", "regressed"):
            ET.SubElement(case, "failure", type=str(r.status), message=message).text = message
        elif r.status in ("no-data", "no-threshold", "too-few"):
            ET.SubElement(case, "skipped", message=f"{r.status}: {message}")
    with atomic_write(path, "wb") as fh:
        ET.ElementTree(root).write(fh, encoding="utf-8", xml_declaration=True)
    return path
