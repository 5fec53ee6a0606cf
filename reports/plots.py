"""The plots of ``report.html``: each fills a matplotlib figure from a report table and says
whether it had data to draw. ``reports.html`` embeds them; matplotlib is imported by the
caller only when a plot is drawn, so that ``reports`` imports fast.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from reports.methods import product
from reports.relations import RELATIONS
from reports.trends import ALL

# Joint names in a fixed order (cadio.truth.joints names them); others follow, sorted.
JOINT_ORDER = ("revolute", "cylindrical", "planar", "slider", "none")


def category_iou(fig: Any, categories: pd.DataFrame) -> bool:
    """Bars of the mean IoU per category (rows of ``completion_categories``), one per method."""
    if categories.empty:
        return False
    wide = categories.pivot_table(index="category", columns="method", values="iou", sort=False)
    ax = fig.add_subplot(1, 1, 1)
    wide.plot.bar(ax=ax, rot=30, ylabel="IoU", xlabel="", ylim=(0, 1), width=0.8)
    ax.tick_params(axis="x", labelsize=8)
    for label in ax.get_xticklabels():
        label.set_horizontalalignment("right")
    ax.legend(fontsize=7, ncols=min(len(wide.columns), 5), loc="upper left")
    return True


def relation_f1(fig: Any, mates: pd.DataFrame) -> bool:
    """Bars of F1 against the CAD per relation over every assembly (``assembly_mates.csv``,
    assembly "all"), with the CAD's count of true pairs above each bar."""
    rows = mates[mates["assembly"] == ALL] if len(mates) else mates
    if rows.empty:
        return False
    rows = rows.set_index("relation").reindex([r for r in RELATIONS if r in set(rows["relation"])])
    ax = fig.add_subplot(1, 1, 1)
    f1 = rows["f1"].astype(float)
    ax.bar(range(len(rows)), f1.fillna(0.0), color="#4c72b0")
    for k, (value, n_cad) in enumerate(zip(f1, rows["n_cad"], strict=True)):
        text = f"n={int(n_cad)}" if value == value else f"n/a\nn={int(n_cad)}"
        ax.text(k, (value if value == value else 0.0) + 0.02, text, ha="center", fontsize=7)
    ax.set_xticks(range(len(rows)), rows.index, rotation=30, ha="right", fontsize=8)
    ax.set(ylabel="F1 against the CAD", ylim=(0, 1.15))
    return True


def joint_agreement(fig: Any, joints: pd.DataFrame) -> bool:
    """The product's joint (columns) against the CAD's (rows), counted over the
    jointed pair views (``assembly_joints.csv``); the diagonal agrees."""
    if joints.empty:
        return False
    names = [j for j in JOINT_ORDER if j in set(joints["cad_joint"]) | set(
        joints["predicted_joint"])]
    names += sorted((set(joints["cad_joint"]) | set(joints["predicted_joint"])) - set(names))
    counts = pd.crosstab(joints["cad_joint"], joints["predicted_joint"]).reindex(
        index=names, columns=names, fill_value=0).to_numpy()
    ax = fig.add_subplot(1, 1, 1)
    ax.imshow(counts, cmap="Greens")
    for (i, j), v in np.ndenumerate(counts):
        ax.text(j, i, str(v), ha="center", va="center", fontsize=9,
                color="white" if v > counts.max() / 2 else "black")
    agree = float(joints["agree"].astype(bool).mean())
    ax.set(title=f"{100 * agree:.0f}% of {len(joints)} jointed pair views agree",
           xticks=range(len(names)), yticks=range(len(names)), xlabel="predicted",
           ylabel="CAD")
    ax.set_xticklabels(names, fontsize=8)
    ax.set_yticklabels(names, fontsize=8)
    ax.title.set_fontsize(9)
    return True


def iou_lines(fig: Any, table: pd.DataFrame, xlabel: str) -> bool:
    """IoU of each method against the view angle or the number of views (category "all")."""
    rows = table[(table["protocol"] == "observed") & (table["category"] == ALL)]
    if rows.empty:
        return False
    ax = fig.add_subplot(1, 1, 1)
    columns = [c for c in rows.columns if c not in ("protocol", "category", "method")]
    for row in rows.to_dict("records"):  # x at positions: string labels make matplotlib log
        ax.plot(range(len(columns)), [row[c] for c in columns], marker="o", label=row["method"])
    ax.set_xticks(range(len(columns)), [str(c) for c in columns])
    ax.set(xlabel=xlabel, ylabel="IoU", ylim=(0, 1))
    ax.legend()
    return True


def relation_accuracy(fig: Any, alls: pd.DataFrame) -> bool:
    """Accuracy of the product's relation method per relation, one bar per input
    (``relations_summary``, category all)."""
    rows = alls[alls["method"] == product()[1]]
    if rows.empty:
        return False
    wide = rows.pivot_table(index="relation", columns="input", values="accuracy")
    wide = wide.reindex([r for r in RELATIONS if r in wide.index])
    wide.plot.bar(ax=fig.add_subplot(1, 1, 1), rot=30, ylabel="accuracy", ylim=(0, 1))
    return True


def confusion(fig: Any, pairs: pd.DataFrame) -> bool:
    """One confusion matrix per relation of the product's answers (ltn on completed points)."""
    given, method = product()
    rows = pairs[(pairs["method"] == method) & (pairs["input"] == given)] \
        if len(pairs) else pairs
    if rows.empty:
        return False
    for k, relation in enumerate(RELATIONS):
        ax = fig.add_subplot(2, 5, k + 1)
        sub = rows[rows["relation"] == relation]
        matrix = pd.crosstab(sub["truth"].astype(bool), sub["predicted"].astype(bool)).reindex(
            index=[False, True], columns=[False, True], fill_value=0)
        counts = matrix.to_numpy()
        ax.imshow(counts, cmap="Blues")
        for (i, j), v in np.ndenumerate(counts):
            ax.text(j, i, str(v), ha="center", va="center", fontsize=8,
                    color="white" if v > counts.max() / 2 else "black")
        ax.set(title=relation, xticks=[0, 1], yticks=[0, 1], xticklabels=["no", "yes"],
               yticklabels=["no", "yes"], xlabel="predicted", ylabel="truth")
    return True


def trends(fig: Any, history: Sequence[tuple[str, pd.DataFrame]],
           metrics: Sequence[str]) -> bool:
    """The headline metrics (category all) over the runs of ``history``, oldest first."""
    ax = fig.add_subplot(1, 1, 1)
    labels = [run_id[:15] for run_id, _ in history]
    drawn = False
    for metric in metrics:
        values = [_value(table, metric) for _, table in history]
        if any(v == v for v in values):  # some value that is not NaN
            ax.plot(range(len(labels)), values, marker="o", label=metric)
            drawn = True
    ax.set_xticks(range(len(labels)), labels, rotation=20)
    ax.set(xlabel="run", ylabel="value", ylim=(0, 1.05))
    if drawn:
        ax.legend()
    return drawn


def _value(table: pd.DataFrame, metric: str) -> float:
    rows = table[(table["metric"] == metric) & (table["category"] == ALL)]
    return float(rows["value"].iloc[0]) if len(rows) else float("nan")


def deviation(fig: Any, image: np.ndarray, tolerance_mm: float, title: str) -> bool:
    """A view's scan-to-CAD deviation (mm, signed: red where there is material the CAD has
    not), and its histogram with the tolerance marked."""
    values = image[np.isfinite(image)]
    if not len(values):
        return False
    limit = 3 * tolerance_mm
    ax = fig.add_subplot(1, 2, 1)
    shown = ax.imshow(np.clip(image, -limit, limit), cmap="RdBu_r", vmin=-limit, vmax=limit)
    ax.set(title=title, xticks=[], yticks=[])
    fig.colorbar(shown, ax=ax, fraction=0.04, label="mm")
    ax = fig.add_subplot(1, 2, 2)
    ax.hist(np.clip(values, -limit, limit), bins=60, color="#777")
    for x in (-tolerance_mm, tolerance_mm):
        ax.axvline(x, color="#c33", lw=1)
    share = float(np.mean(np.abs(values) <= tolerance_mm))
    ax.set(xlabel="scan to CAD, mm", ylabel="pixels",
           title=f"{share:.1%} within +/-{tolerance_mm:g} mm")
    return True
