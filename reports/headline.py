"""The completion headline: the mean IoU per distinct shape, over parts scored where they were
placed, with an interval that resamples source files.

The plain per-part mean (``completion_categories.csv``) counts what a QA engineer would not:
a shape repeated 63 times in one rack weighs 63 times (``reports.shapes``), and a part hidden
in its assembly is rendered again alone, filling the frame, and scored there, where it was
never placed. So the headline is taken over the rows of parts scored where they were placed
(``placed``) and weighs every distinct shape once; its interval draws the source files with
replacement (``reports.intervals.shape_mean_interval``), since the parts of one file are not
independent; the counts of parts, shapes and files stand beside it.

``runs/<run_id>/completion_headline.csv``: one row per category (and ``all``, last), method
and protocol, columns ``HEADLINE_COLUMNS``:

- ``iou``, ``iou_low``, ``iou_high``: the headline and its 95% interval over files;
  ``n_parts``, ``n_shapes``, ``n_files``: what it rests on.
- ``iou_outside``: the same mean with the truth outside the grid counted as missed
  (``iou_counting_outside``; ``iou`` scores the part inside the grid its view placed).
- ``iou_parts``: the per-part mean over the same placed parts.
- ``n_rerendered``, ``iou_rerendered``: parts of a multi-part file scored only alone, re-rendered
  because their assembly hid them (per-part mean); not in the headline.
- ``n_parts_all``, ``iou_all_contexts``: the per-part mean over every context, as
  ``completion_categories.csv`` has it.

Held-out parts, single views, as every completion table. Pure pandas and NumPy.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pandas as pd

from cadio.errors import InputFileError
from cadio.workspace import atomic_write
from reports.completion import ALL, HELD_OUT, _sorted, labelled_methods
from reports.intervals import shape_mean_interval
from reports.shapes import DEFAULT_SHAPES, ShapeConfig, shape_keys
from reports.tables import markdown_table

HEADLINE_FILE = "completion_headline.csv"
HEADLINE_COLUMNS = ("category", "method", "protocol", "n_parts", "n_shapes", "n_files", "iou",
                    "iou_low", "iou_high", "iou_outside", "iou_parts", "n_rerendered",
                    "iou_rerendered", "n_parts_all", "iou_all_contexts")
PLACED_CONTEXTS = ("pair", "assembly")
OURS_PROTOCOL = "observed"


def iou_counting_outside(iou: npt.ArrayLike, missing: npt.ArrayLike,
                         coverage: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """IoU with the truth outside the grid counted as missed.

    ``iou`` and ``missing`` score a prediction against the truth inside the grid the view
    placed, and ``coverage`` is the share of the part's volume inside that grid, so with T the
    truth's voxels inside, T (1 - missing) are hit, the union is T (1 - missing) / iou, and
    T (1 / coverage - 1) lie outside: IoU = (1 - missing) / ((1 - missing) / iou
    + 1 / coverage - 1). Nothing hit, or no truth inside, gives 0; an unknown coverage leaves
    ``iou`` as it is.

    Args:
        iou, missing, coverage: arrays of one shape, in [0, 1] (NaN allowed).

    Returns:
        The IoU, same shape.
    """
    iou, missing, coverage = (np.asarray(a, dtype=np.float64) for a in (iou, missing, coverage))
    hit = 1.0 - np.nan_to_num(missing, nan=1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        counted = hit / (hit / iou + 1.0 / coverage - 1.0)
    counted = np.where((hit <= 0) | (coverage <= 0), 0.0, counted)
    return np.asarray(np.where(np.isnan(coverage), iou, counted), dtype=np.float64)


def placed(parts: pd.DataFrame, n_solids: pd.Series) -> pd.Series:
    """Whether each row scores its part where it was placed: in a pair scene or inside its
    assembly; or alone when its file holds that part only (the library gives it alone). A part
    of a multi-part file seen alone was rendered again because its assembly hid it (or its
    assembly's capture failed): not where it was placed.

    Args:
        parts: ``completion_parts`` rows (part_id, context).
        n_solids: part id -> the solids of its source file (a part it lacks counts as one of
            several).
    """
    single = parts["part_id"].astype(str).map(n_solids).fillna(0).astype("int64") == 1
    return parts["context"].isin(PLACED_CONTEXTS) | ((parts["context"] == "alone") & single)


def headline_table(parts: pd.DataFrame, geometry: pd.DataFrame, split: str = HELD_OUT,
                   n_views: int = 1, shapes: ShapeConfig = DEFAULT_SHAPES,
                   seed: int = 0) -> pd.DataFrame:
    """``completion_headline.csv``'s table (see the module docstring).

    Args:
        parts: ``completion_parts`` rows.
        geometry: ``reports.shapes.part_geometry`` of the workspace (a part it lacks is a
            shape and a file of its own).
        split, n_views: the rows counted (held-out parts, single views).
        seed: of the intervals' draws.

    Returns:
        Columns ``HEADLINE_COLUMNS``, ``all`` after the categories.
    """
    rows = parts[(parts["split"] == split) & (parts["n_views"] == n_views)]
    if rows.empty:
        return pd.DataFrame(columns=list(HEADLINE_COLUMNS))
    known = geometry.set_index(geometry["part_id"].astype(str))
    ids = rows["part_id"].astype(str)
    rows = rows.assign(
        placed=placed(rows, known["n_solids"]),
        iou_outside=iou_counting_outside(rows["iou"], rows["missing"], rows["coverage"]),
        shape=part_shapes(ids, geometry, shapes), file=_or_own(ids, known["source"]))
    rows = pd.concat([rows, rows.assign(category=ALL)], ignore_index=True)
    table = [_figures(group, category, method, protocol, seed)
             for (category, method, protocol), group
             in rows.groupby(["category", "method", "protocol"], sort=True)]
    frame = pd.DataFrame(table, columns=list(HEADLINE_COLUMNS))
    return _sorted(frame, ["category", "method", "protocol"])


def part_shapes(part_ids: pd.Series, geometry: pd.DataFrame,
                shapes: ShapeConfig = DEFAULT_SHAPES) -> pd.Series:
    """Each part's shape key (``reports.shapes.shape_keys``); a part ``geometry`` lacks is a
    shape of its own."""
    return _or_own(part_ids.astype(str), shape_keys(geometry, shapes))


def _or_own(ids: pd.Series, mapping: pd.Series) -> pd.Series:
    """``mapping`` of each id, or the id itself where it has none."""
    mapped = ids.map(mapping).astype(object)
    return mapped.where(mapped.notna(), ids).astype(str)


def _figures(rows: pd.DataFrame, category: str, method: str, protocol: str,
             seed: int) -> dict[str, object]:
    """One row of the headline table: the figures of one category, method and protocol."""
    mine = rows[rows["placed"]]
    per_part = mine.groupby("part_id").agg(iou=("iou", "mean"), outside=("iou_outside", "mean"),
                                           shape=("shape", "first"), file=("file", "first"))
    low, high, files = shape_mean_interval(per_part["iou"], per_part["shape"], per_part["file"],
                                           seed=seed)
    again = rows[~rows["placed"] & ~rows["part_id"].isin(set(mine["part_id"]))]
    return {"category": category, "method": method, "protocol": protocol,
            "n_parts": len(per_part), "n_shapes": per_part["shape"].nunique(), "n_files": files,
            "iou": _shape_mean(per_part, "iou"), "iou_low": low, "iou_high": high,
            "iou_outside": _shape_mean(per_part, "outside"),
            "iou_parts": _mean(per_part["iou"]), "n_rerendered": again["part_id"].nunique(),
            "iou_rerendered": _mean(again.groupby("part_id")["iou"].mean()),
            "n_parts_all": rows["part_id"].nunique(),
            "iou_all_contexts": _mean(rows.groupby("part_id")["iou"].mean())}


def _shape_mean(per_part: pd.DataFrame, column: str) -> float:
    """Mean over shapes of the mean over each shape's parts."""
    return _mean(per_part.groupby("shape")[column].mean())


def _mean(values: pd.Series) -> float:
    return float(values.mean()) if values.notna().any() else math.nan


HEADLINE_NOTE = (
    "Held-out parts, one view. `iou`: the mean per distinct shape (one volume, area and face "
    "count) over the parts scored where they were placed (in a pair scene, inside their "
    "assembly, or alone where their file holds them alone), with its 95% interval resampling "
    "the source files (`files`). `iou_outside`: the same with the truth outside the grid "
    "counted as missed. `iou_parts`: the per-part mean of those parts. `rerendered`: parts of "
    "a multi-part file scored only alone, re-rendered because their assembly hid them (not in "
    "the headline). `all_contexts`: the per-part mean over every context, as the category "
    "table has it.")


def display_table(table: pd.DataFrame, protocol: str = OURS_PROTOCOL) -> pd.DataFrame:
    """The headline table of one protocol as read: IoUs in %, the interval in one cell."""
    rows = labelled_methods(table[table["protocol"] == protocol])

    def pct(column: str) -> pd.Series:
        return rows[column].map(lambda v: "-" if v != v else f"{100 * v:.1f}")

    return pd.DataFrame({
        "category": rows["category"], "method": rows["method"], "parts": rows["n_parts"],
        "shapes": rows["n_shapes"], "files": rows["n_files"], "iou": pct("iou"),
        "95% interval": [f"{100 * lo:.1f} to {100 * hi:.1f}" if lo == lo else "-"
                         for lo, hi in zip(rows["iou_low"], rows["iou_high"], strict=True)],
        "iou_outside": pct("iou_outside"), "iou_parts": pct("iou_parts"),
        "rerendered": rows["n_rerendered"], "iou_rerendered": pct("iou_rerendered"),
        "parts_all": rows["n_parts_all"], "iou_all_contexts": pct("iou_all_contexts")})


def headline_markdown(table: pd.DataFrame) -> str:
    """``completion.md``'s headline section (observed protocol)."""
    lines = ["", "## The headline: IoU (%) per distinct shape, parts scored where they were "
             "placed (protocol: observed)", "", HEADLINE_NOTE, ""]
    shown = display_table(table)
    lines.append(markdown_table(shown) if len(shown) else "No held-out part scored.")
    return "\n".join(lines) + "\n"


def write_headline(run_dir: Path, table: pd.DataFrame) -> Path:
    """``completion_headline.csv`` in ``run_dir``, atomically (NaN as an empty field).

    Raises:
        ValueError: the table does not have the columns ``HEADLINE_COLUMNS``.
    """
    if tuple(table.columns) != HEADLINE_COLUMNS:
        raise ValueError(f"the headline table must have the columns {HEADLINE_COLUMNS}")
    path = Path(run_dir) / HEADLINE_FILE
    with atomic_write(path, "w") as fh:
        table.to_csv(fh, index=False)
    return path


def read_headline(run_dir: Path) -> pd.DataFrame:
    """``completion_headline.csv`` of ``run_dir`` (empty, with its columns, where the run has
    none: a run written before the headline was).

    Raises:
        InputFileError: the file has other columns.
    """
    path = Path(run_dir) / HEADLINE_FILE
    if not path.is_file():
        return pd.DataFrame(columns=list(HEADLINE_COLUMNS))
    frame = pd.read_csv(path, dtype={"category": "str", "method": "str", "protocol": "str"},
                        keep_default_na=False, na_values=[""])
    if tuple(frame.columns) != HEADLINE_COLUMNS:
        raise InputFileError(path, f"columns {tuple(frame.columns)}, not {HEADLINE_COLUMNS}")
    return frame
