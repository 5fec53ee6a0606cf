"""The completion report: per-part scores, per-category means, and the run report's tables.

Two files other tools read (DESIGN.md, "Report files": names and columns are a contract):

- ``runs/<run_id>/completion_parts.parquet``: one row per part x context x method x protocol
  x n_views x view, columns and dtypes ``PARTS_SCHEMA`` (the keys, ``reports.metrics.METRICS``,
  then ``coverage``: the share of the part's volume inside the grid the camera's view placed).
  The context is where the camera saw the part: ``alone``, in a ``pair`` scene, or inside an
  ``assembly`` as placed (occluded by its neighbours).
- ``runs/<run_id>/completion_categories.csv``: one row per category x method x protocol,
  columns ``CATEGORY_COLUMNS``: n_parts and the mean of every metric (and of the coverage)
  over the held-out parts scored from a single view, plus the category ``all``.
- ``runs/<run_id>/completion_contexts.csv``: the same means per category x context
  (``CONTEXT_COLUMNS``): how the methods do on parts in pairs and inside assemblies.

``completion.md`` opens with the parts per category: with the coverage of the library
(``reports.coverage``: parts ingested, parts scored and their share) where the run has it, and
per split.

Every mean here is taken first over the views of a part, then over parts, so a part scored
from 125 views weighs as much as a part scored from one. ``all`` is the mean over every part
(a category with more parts weighs more), not the mean of the category means. NaN metrics (the
composition error and Chamfer distance of an empty prediction) are left out of the means and
counted in the Markdown; the other metrics score an empty prediction as a failure (IoU 0,
missing 1, F-score 0), so a failed part never drops out of the IoU.

Protocols: ``observed`` places the input grid from the observed points only (what a camera
knows); ``oracle-box`` uses the truth's grid, as the paper did. Every table names its protocol.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cadio.errors import InputFileError
from cadio.records import Category
from cadio.workspace import atomic_path, atomic_write
from reports.methods import completion_order, method_labels
from reports.metrics import METRICS, BoolGrid, Truth, part_metrics
from reports.tables import markdown_table

PARTS_FILE = "completion_parts.parquet"
CATEGORIES_FILE = "completion_categories.csv"
CONTEXTS_FILE = "completion_contexts.csv"
MARKDOWN_FILE = "completion.md"
KEY_SCHEMA = {"part_id": "str", "category": "str", "split": "str", "context": "str",
              "method": "str", "protocol": "str", "n_views": "int64", "view_deg": "float64"}
PARTS_SCHEMA = {**KEY_SCHEMA, **dict.fromkeys(METRICS, "float64"), "coverage": "float64"}
MEANS = (*METRICS, "coverage")
CATEGORY_COLUMNS = ("category", "method", "protocol", "n_parts", *MEANS)
CONTEXT_COLUMNS = ("category", "context", "method", "protocol", "n_parts", *MEANS)
CONTEXTS = ("alone", "pair", "assembly")

PROTOCOLS = ("observed", "oracle-box")
ALL = "all"
HELD_OUT = "test"
SPLITS = ("train", "val", "test")  # cadio.truth.scenes.SPLITS, not imported: the truth room
# Five bins of 25 of the 125 views 2.88 degrees apart; the paper's Figure 6 shows five angles.
VIEW_BIN_DEG = 72.0

# The paper's figures: a single view, the truth's grid (oracle-box), 256^3, its own parts.
PAPER_PROTOCOL = "oracle-box"
PAPER_OVERLAP_PCT = {  # Table I: projection overlap on X-Y, Y-Z, Z-X
    Category.BRAKES.value: (60.0, 47.0, 86.0), Category.CASTERS.value: (79.0, 12.0, 46.0),
    Category.FASTENERS.value: (43.0, 82.0, 72.0), Category.MOTION.value: (66.0, 77.0, 87.0)}
PAPER_IOU_PCT = {  # Table II: IoU of the paper's method and of 3D-R2N2
    Category.BRAKES.value: (70.48, 64.2), Category.CASTERS.value: (68.39, 59.3),
    Category.FASTENERS.value: (67.12, 53.3), Category.MOTION.value: (76.46, 73.85)}
# The abstract's overall IoU; the mean of Table II's rows is 70.61, and the paper does not say
# how 57.23 was taken. Reported as printed, with that note.
PAPER_OVERALL_IOU_PCT = 57.23
_PAPER_SETTING = f"the paper: {PAPER_PROTOCOL}, one view, its own parts"
_LIBRARY_TITLE = ("### Parts per category: ingested, scored (coverage_parts = parts_scored / "
                   "parts_ingested) and per split")


@dataclass(frozen=True)
class CompletionCase:
    """What one prediction was made for: the key columns of ``completion_parts.parquet``.

    protocol: one of ``PROTOCOLS``. n_views: input views (1, 2, 4, 8). view_deg: azimuth about
    Z of the first input view, degrees in [0, 360) (view k of the 125-view circle: 2.88 k).
    context: where the part was seen (``CONTEXTS``). coverage: share of its volume in the grid.
    """

    part_id: str
    category: str
    split: str
    method: str
    protocol: str
    n_views: int
    view_deg: float
    context: str = "pair"
    coverage: float = math.nan

    def __post_init__(self) -> None:
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"unknown protocol {self.protocol!r}; known: {PROTOCOLS}")
        if self.n_views < 1:
            raise ValueError(f"n_views must be at least 1, got {self.n_views}")

    def score(self, pred: BoolGrid, truth: BoolGrid | Truth, voxel_mm: float) -> dict[str, Any]:
        """This case's row: its keys and ``reports.metrics.part_metrics`` (``truth`` prepared
        once as a ``reports.metrics.Truth`` where many predictions are scored against it)."""
        scores = truth.metrics(pred) if isinstance(truth, Truth) else part_metrics(
            pred, truth, voxel_mm)
        return {**asdict(self), **scores}


def parts_frame(rows: Iterable[Mapping[str, Any]]) -> pd.DataFrame:
    """Rows (e.g. of ``CompletionCase.score``) as a frame with the dtypes of ``PARTS_SCHEMA``.

    Raises:
        ValueError: a column is missing, a protocol is unknown, or a key repeats.
    """
    return _typed_parts(pd.DataFrame(list(rows), columns=list(PARTS_SCHEMA)))


def _typed_parts(frame: pd.DataFrame) -> pd.DataFrame:
    # Runs written before parts had a context or a coverage read as parts of pair scenes.
    frame = frame.assign(**{c: frame[c] if c in frame else v
                            for c, v in (("context", "pair"), ("coverage", math.nan))})
    absent = [c for c in PARTS_SCHEMA if c not in frame.columns]
    if absent:
        raise ValueError(f"completion parts lack the columns {absent}")
    typed = frame[list(PARTS_SCHEMA)].astype(PARTS_SCHEMA).reset_index(drop=True)
    unknown = sorted(set(typed["protocol"]) - set(PROTOCOLS))
    if unknown:
        raise ValueError(f"unknown protocols {unknown}; known: {PROTOCOLS}")
    if typed.duplicated(list(KEY_SCHEMA)).any():
        raise ValueError("a part x context x method x protocol x n_views x view is scored twice")
    return typed


def write_completion_parts(run_dir: Path, parts: pd.DataFrame) -> Path:
    """``completion_parts.parquet`` in ``run_dir``, atomically; returns its path.

    Raises:
        ValueError: as ``parts_frame``.
    """
    typed, path = _typed_parts(parts), run_dir / PARTS_FILE
    with atomic_path(path) as tmp:
        typed.to_parquet(tmp, index=False)
    return path


def read_completion_parts(run_dir: Path) -> pd.DataFrame:
    """The parts file of ``run_dir`` with the dtypes of ``PARTS_SCHEMA``.

    Raises:
        InputFileError: the file lacks a column, or holds an unknown protocol or a repeated key.
    """
    path = run_dir / PARTS_FILE
    try:
        return _typed_parts(pd.read_parquet(path))
    except ValueError as exc:
        raise InputFileError(path, str(exc)) from exc


def category_means(parts: pd.DataFrame, split: str = HELD_OUT, n_views: int = 1) -> pd.DataFrame:
    """The categories file's table: per category (and ``all``), method and protocol, n_parts
    and the mean of each metric over the parts of ``split`` scored from ``n_views`` views
    (means over a part's views first, then over parts; NaN left out). Columns
    ``CATEGORY_COLUMNS``, ``all`` last."""
    rows = parts[(parts["split"] == split) & (parts["n_views"] == n_views)]
    keys = ["category", "method", "protocol"]
    return _part_means(_with_all(rows), keys, list(MEANS))[list(CATEGORY_COLUMNS)]


def context_means(parts: pd.DataFrame, split: str = HELD_OUT, n_views: int = 1) -> pd.DataFrame:
    """``category_means`` per context as well (``CONTEXT_COLUMNS``): a part seen in a pair and
    inside an assembly counts in each."""
    rows = parts[(parts["split"] == split) & (parts["n_views"] == n_views)]
    keys = ["category", "context", "method", "protocol"]
    return _part_means(_with_all(rows), keys, list(MEANS))[list(CONTEXT_COLUMNS)]


def _with_all(rows: pd.DataFrame) -> pd.DataFrame:
    return pd.concat([rows, rows.assign(category=ALL)], ignore_index=True)


def _part_means(rows: pd.DataFrame, keys: list[str], values: list[str]) -> pd.DataFrame:
    """Mean of ``values`` over the rows of each part, then over the parts of each ``keys``
    group (NaN left out at both steps); ``n_parts`` counts the parts."""
    per_part = rows.groupby([*keys, "part_id"], sort=True)[values].mean().reset_index()
    groups = per_part.groupby(keys, sort=True)
    table = groups[values].mean().astype("float64")
    table.insert(0, "n_parts", groups.size().astype("int64"))
    return _sorted(table.reset_index(), keys)


def _sorted(table: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """Rows by ``keys``, with ``all`` after the categories and ours and the baselines before
    any other method."""
    return table.sort_values(keys, key=_sort_key, kind="stable").reset_index(drop=True)


def _sort_key(column: pd.Series) -> pd.Series:
    if column.name == "category":
        return column.map(lambda c: f"1{c}" if c == ALL else f"0{c}")
    if column.name == "method":
        rank = {m: i for i, m in enumerate(completion_order())}
        return column.map(lambda m: f"{rank.get(m, len(rank))}{m}")
    return column


def write_completion_categories(run_dir: Path, categories: pd.DataFrame) -> Path:
    """``completion_categories.csv`` in ``run_dir``, atomically (NaN as an empty field)."""
    if tuple(categories.columns) != CATEGORY_COLUMNS:
        raise ValueError(f"categories must have the columns {CATEGORY_COLUMNS}")
    path = run_dir / CATEGORIES_FILE
    with atomic_write(path, "w") as fh:
        categories.to_csv(fh, index=False)
    return path


def read_completion_categories(run_dir: Path) -> pd.DataFrame:
    """The categories file of ``run_dir``, typed as ``category_means`` returns it."""
    path = run_dir / CATEGORIES_FILE
    frame = pd.read_csv(path, dtype={"category": "str", "method": "str", "protocol": "str"},
                        keep_default_na=False, na_values=[""])
    if "coverage" not in frame:  # written before the coverage was reported
        frame["coverage"] = math.nan
    if tuple(frame.columns) != CATEGORY_COLUMNS:
        raise InputFileError(path, f"columns {tuple(frame.columns)}, not {CATEGORY_COLUMNS}")
    return frame.astype({"n_parts": "int64", **dict.fromkeys(MEANS, "float64")})


def iou_by_view_angle(parts: pd.DataFrame, bin_deg: float = VIEW_BIN_DEG,
                      split: str = HELD_OUT, metric: str = "iou") -> pd.DataFrame:
    """Mean ``metric`` of single-view predictions in bins of the view's azimuth (the paper's
    Figure 6): per protocol, category (and ``all``) and method, one column per bin, labelled
    "lo-hi" in degrees (half-open, [lo, hi)).

    Raises:
        ValueError: a bin width outside (0, 360].
    """
    if not 0 < bin_deg <= 360:
        raise ValueError(f"bin width must be in (0, 360] degrees, got {bin_deg}")
    n_bins = math.ceil(360.0 / bin_deg - 1e-9)
    rows = parts[(parts["split"] == split) & (parts["n_views"] == 1)]
    # The tolerance keeps a view at 25 * 2.88 = 72.00000000000001 degrees... and one computed
    # as 71.99999999999999 in the bin that starts at 72.
    index = np.floor((rows["view_deg"] % 360.0) / bin_deg + 1e-9).astype("int64")
    labels = [f"{i * bin_deg:g}-{min((i + 1) * bin_deg, 360.0):g}" for i in range(n_bins)]
    table = _pivot(rows.assign(view_bin=index.clip(upper=n_bins - 1)), "view_bin", metric,
                   range(n_bins))
    return table.rename(columns=dict(enumerate(labels)))


def iou_by_n_views(parts: pd.DataFrame, split: str = HELD_OUT,
                   metric: str = "iou") -> pd.DataFrame:
    """Mean ``metric`` against the number of input views: per protocol, category (and
    ``all``) and method, one column per number of views present ("1", "2", "4", "8")."""
    rows = parts[parts["split"] == split]
    counts = sorted(int(n) for n in rows["n_views"].unique())
    table = _pivot(rows, "n_views", metric, counts)
    return table.rename(columns={n: str(n) for n in counts})


def _pivot(rows: pd.DataFrame, column: str, metric: str, values: Iterable[int]) -> pd.DataFrame:
    keys = ["protocol", "category", "method"]
    means = _part_means(_with_all(rows), [*keys, column], [metric])
    wide = means.pivot_table(index=keys, columns=column, values=metric, dropna=False,
                             sort=False).reindex(columns=list(values))
    wide.columns.name = None
    return wide.reset_index()


def paper_iou_table(categories: pd.DataFrame) -> pd.DataFrame:
    """IoU (%) per protocol and category: every method of the run beside the paper's Table II
    (``paper``: its method, ``paper_r2n2``: 3D-R2N2; ``all`` gets the abstract's 57.23)."""
    wide = _wide(categories, lambda rows: rows["iou"] * 100)
    cats = wide["category"]
    wide["paper"] = [PAPER_OVERALL_IOU_PCT if c == ALL else PAPER_IOU_PCT.get(c, (np.nan,))[0]
                     for c in cats]
    wide["paper_r2n2"] = [PAPER_IOU_PCT.get(c, (np.nan, np.nan))[1] for c in cats]
    return wide


def paper_overlap_table(categories: pd.DataFrame) -> pd.DataFrame:
    """Projection overlap (%) per protocol and category as "XY/YZ/ZX" cells, every method of
    the run beside the paper's Table I (``paper``)."""
    planes = ["overlap_xy", "overlap_yz", "overlap_zx"]
    wide = _wide(categories, lambda rows: rows[planes].mul(100).apply(_triple, axis=1))
    wide["paper"] = [_triple(pd.Series(PAPER_OVERLAP_PCT.get(c, (np.nan,) * 3)))
                     for c in wide["category"]]
    return wide


def _triple(values: pd.Series) -> str:
    return "/".join("-" if math.isnan(v) else f"{v:.0f}" for v in values)


def _wide(categories: pd.DataFrame,
          cell: Callable[[pd.DataFrame], pd.Series]) -> pd.DataFrame:
    """One row per protocol and category, n_parts (the most of any method), one column per
    method holding ``cell(rows)``."""
    frame = categories.assign(cell=cell(categories))
    keys = ["protocol", "category"]
    wide = frame.pivot(index=keys, columns="method", values="cell")
    methods = _sorted(categories.drop_duplicates("method"), ["method"])["method"]
    wide = wide.reindex(columns=list(methods)).rename(columns=method_labels())
    wide.columns.name = None
    wide.insert(0, "n_parts", frame.groupby(keys)["n_parts"].max())
    return _sorted(wide.reset_index(), keys)


def labelled_methods(table: pd.DataFrame) -> pd.DataFrame:
    """``table`` with its ``method`` column (where it has one) named for reading
    (``CompletionMethod.label``)."""
    if "method" not in table:
        return table
    return table.assign(method=table["method"].replace(method_labels()))


def split_sizes(parts: pd.DataFrame) -> pd.DataFrame:
    """Parts per category (and ``all``) and split: distinct part ids scored."""
    distinct = _with_all(parts.drop_duplicates(["part_id", "category"]))
    table = pd.crosstab(distinct["category"], distinct["split"])
    table = table.reindex(columns=[s for s in SPLITS if s in table.columns]
                          + sorted(set(table.columns) - set(SPLITS)), fill_value=0)
    table.columns.name = None
    rows = sorted(table.index, key=lambda c: (c == ALL, c))
    return table.reindex(rows).reset_index()


def _parts_table(parts: pd.DataFrame, library: pd.DataFrame | None) -> pd.DataFrame:
    """Parts per category: ingested, scored and their share (when known), then per split."""
    splits = split_sizes(parts) if len(parts) else pd.DataFrame(columns=["category"])
    if library is None:
        return splits
    table = _fmt(library, 3).merge(splits, on="category", how="left")
    split_columns = [c for c in table.columns if c not in library.columns]
    table[split_columns] = table[split_columns].fillna(0).astype("int64")
    return table


def completion_markdown(parts: pd.DataFrame, split: str = HELD_OUT,
                        library: pd.DataFrame | None = None) -> str:
    """The run report's completion section: the parts per category (with ``library``, the
    ``reports.coverage.part_coverage`` table: parts ingested, scored and their share) and
    split, empty predictions, and per protocol the category means, the paper comparisons, IoU
    against view angle and number of views."""
    if parts.empty:
        lines = ["## Completion", "", "No completion scores in this run.", ""]
        if library is not None:
            lines += [_LIBRARY_TITLE, "", markdown_table(_parts_table(parts, library)), ""]
        return "\n".join(lines)
    categories = category_means(parts, split)
    lines = [
        "## Completion", "",
        f"Scores of the held-out split ({split!r}); category means and the comparisons with "
        "the paper are over single-view predictions. Means are over the views of a part first, "
        "then over parts; `all` is over every part. Protocols: `observed` places the input "
        "grid from the observed points only, `oracle-box` uses the truth's grid (the paper's "
        f"figures are {PAPER_PROTOCOL}, single view, 256^3, on the paper's own parts; its "
        f"overall {PAPER_OVERALL_IOU_PCT}% is the abstract's, where its Table II averages "
        "70.61%).", "",
        _LIBRARY_TITLE if library is not None else "### Parts per split and category", "",
        markdown_table(_parts_table(parts, library)), "",
    ]
    lines += _empty_predictions(parts)
    for protocol in [p for p in PROTOCOLS if p in set(parts["protocol"])]:
        lines += _protocol_section(parts, categories, protocol, split)
    lines += _context_section(parts, split)
    return "\n".join(lines) + "\n"


def context_iou_table(contexts: pd.DataFrame) -> pd.DataFrame:
    """IoU (%) per protocol, context and category, one column per method, with the mean
    coverage (%) of the parts' grids."""
    frame = contexts.assign(cell=contexts["iou"] * 100)
    keys = ["protocol", "context", "category"]
    wide = frame.pivot(index=keys, columns="method", values="cell")
    methods = _sorted(contexts.drop_duplicates("method"), ["method"])["method"]
    wide = wide.reindex(columns=list(methods)).rename(columns=method_labels())
    wide.columns.name = None
    wide.insert(0, "coverage", frame.groupby(keys)["coverage"].mean() * 100)
    wide.insert(0, "n_parts", frame.groupby(keys)["n_parts"].max())
    return _sorted(wide.reset_index(), keys)


def _context_section(parts: pd.DataFrame, split: str) -> list[str]:
    table = context_iou_table(context_means(parts, split))
    if table.empty:
        return []
    return ["### Where the parts were seen: alone, in pairs, inside assemblies", "",
            "Single-view IoU (%) of the held-out parts by the context the camera saw them in; "
            "coverage: the share of the part inside the grid its view placed (a part hidden "
            "behind others can reach out of it).", "", markdown_table(_fmt(table, 2)), ""]


def _empty_predictions(parts: pd.DataFrame) -> list[str]:
    empty = parts.assign(empty=parts["composition_error"].isna())
    if not empty["empty"].any():
        return ["No prediction is empty.", ""]
    table = (empty.groupby(["protocol", "method", "split"], sort=True)
             .agg(predictions=("empty", "size"), empty=("empty", "sum")).reset_index())
    n = int(table["empty"].sum())
    return [f"{n} {'prediction is' if n == 1 else 'predictions are'} empty: scored IoU 0, "
            "missing 1, F-score 0 and Chamfer-L1 the part's diagonal, with composition_error "
            "undefined (NaN) and left out of its mean.", "",
            markdown_table(table[table["empty"] > 0]), ""]


def _protocol_section(parts: pd.DataFrame, categories: pd.DataFrame, protocol: str,
                      split: str) -> list[str]:
    mine = parts[parts["protocol"] == protocol]
    cats = categories[categories["protocol"] == protocol]
    tables = [
        ("Per category", _fmt(labelled_methods(cats), 3)),
        (f"IoU (%) beside the paper's Table II ({_PAPER_SETTING})",
         _fmt(paper_iou_table(cats), 2)),
        (f"Projection overlap (%) XY/YZ/ZX beside the paper's Table I ({_PAPER_SETTING})",
         paper_overlap_table(cats)),
        (f"IoU against the view angle, bins of {VIEW_BIN_DEG:g} degrees",
         _fmt(iou_by_view_angle(mine, split=split), 3)),
        ("IoU against the number of views", _fmt(iou_by_n_views(mine, split=split), 3)),
    ]
    lines = [f"### Protocol: {protocol}", ""]
    for title, table in tables:
        lines += [f"#### {title}, protocol: {protocol}", "",
                  markdown_table(table.drop(columns="protocol")), ""]
    return lines


def _fmt(frame: pd.DataFrame, digits: int) -> pd.DataFrame:
    """Floats rounded for reading, NaN as "-"."""
    out = frame.astype(object)
    for col in frame.columns[[pd.api.types.is_float_dtype(t) for t in frame.dtypes]]:
        out[col] = ["-" if math.isnan(v) else f"{v:.{digits}f}" for v in frame[col]]
    return out


def write_completion(run_dir: Path, parts: pd.DataFrame,
                     library: pd.DataFrame | None = None) -> Path:
    """The parts file, the categories and contexts files and ``completion.md`` (with
    ``library``, the ``reports.coverage.part_coverage`` table, where given) in ``run_dir``;
    returns the Markdown path."""
    write_completion_parts(run_dir, parts)
    write_completion_categories(run_dir, category_means(parts))
    with atomic_write(run_dir / CONTEXTS_FILE, "w") as fh:
        context_means(parts).to_csv(fh, index=False)
    with atomic_write(run_dir / MARKDOWN_FILE, "w") as fh:
        fh.write(completion_markdown(parts, library=library))
    return run_dir / MARKDOWN_FILE
