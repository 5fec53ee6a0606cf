"""``report.html``: one self-contained page per run (plots inline as PNG), read the next morning.

Sections: the run and its failures, the threshold checks, completion per category beside the
paper's Tables I and II, relations per relation and input beside Table III, the assemblies
against their CAD mates and joints, and the trends over earlier runs. Every plot is an ``img``
with a ``data-plot`` name; a section without data says so instead. matplotlib is imported only
when a plot is drawn, so that ``reports`` imports fast.
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Callable, Sequence
from typing import Any

import pandas as pd

from reports.completion import (
    HELD_OUT,
    category_means,
    iou_by_n_views,
    iou_by_view_angle,
    paper_iou_table,
    paper_overlap_table,
)
from reports.relations import RELATIONS, accuracy_table, calibration_table

PLOTS = ("category_iou", "iou_by_view_angle", "iou_by_n_views", "relation_accuracy",
         "confusion", "trends")
STYLE = """
body{font-family:system-ui,sans-serif;margin:2em;max-width:1300px;color:#222}
h1{margin-bottom:0}h2{border-bottom:2px solid #ccc;padding-bottom:4px;margin-top:2em}
table{border-collapse:collapse;margin:0.5em 0 1em;font-size:13px}
th,td{border:1px solid #ccc;padding:3px 7px;text-align:right}th{background:#f2f2f2}
td:first-child,th:first-child{text-align:left}
.pass{background:#d9f2d9}.fail,.regressed{background:#f8d0d0}.too-few,.no-data,
.no-threshold{background:#eee;color:#666}.nodata{color:#888;font-style:italic}
img{max-width:100%;border:1px solid #ddd;margin:0.5em 0}.banner{padding:8px;font-weight:bold}
"""


class Page:
    """An HTML page built section by section."""

    def __init__(self, title: str) -> None:
        self.parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
                      f"<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>",
                      f"<h1>{html.escape(title)}</h1>"]

    def heading(self, text: str, level: int = 2) -> None:
        self.parts.append(f"<h{level}>{html.escape(text)}</h{level}>")

    def text(self, text: str, css: str = "") -> None:
        self.parts.append(f"<p class='{css}'>{html.escape(text)}</p>")

    def table(self, frame: pd.DataFrame | None, digits: int = 3, status: bool = False) -> None:
        if frame is None or frame.empty:
            self.text("no data", "nodata")
            return
        out = frame.to_html(index=False, na_rep="-", float_format=lambda v: f"{v:.{digits}f}",
                            border=0)
        if status:  # colour each row by its status cell
            for name in ("pass", "fail", "regressed", "too-few", "no-data", "no-threshold"):
                out = out.replace(f"<td>{name}</td>", f"<td class='{name}'>{name}</td>")
        self.parts.append(out)

    def plot(self, name: str, alt: str, draw: Callable[[Any], bool]) -> None:
        """``draw(figure)`` fills a matplotlib figure and says whether it had data."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig = plt.figure(figsize=(11, 4.2))
        try:
            if not draw(fig):
                self.text(f"{alt}: no data", "nodata")
                return
            buf = io.BytesIO()
            fig.tight_layout()
            fig.savefig(buf, format="png", dpi=80)
        finally:
            plt.close(fig)
        data = base64.b64encode(buf.getvalue()).decode()
        self.parts.append(f"<img data-plot='{name}' alt='{html.escape(alt)}' "
                          f"src='data:image/png;base64,{data}'>")

    def render(self) -> str:
        return "\n".join([*self.parts, "</body></html>"])


# ---------------------------------------------------------------- sections


def header(page: Page, run: dict[str, Any], checks: pd.DataFrame, problems: pd.DataFrame) -> None:
    """Run facts, stage times, the verdict, and every input that failed with its reason."""
    failed = checks[checks["status"].isin(["fail", "regressed"])]
    verdict = (f"{len(failed)} threshold checks failed" if len(failed)
               else "every threshold check passed")
    page.parts.append(f"<div class='banner {'fail' if len(failed) else 'pass'}'>"
                      f"{html.escape(verdict)}</div>")
    page.table(pd.DataFrame([{"item": k, "value": str(v)} for k, v in run.items()]))
    page.heading("Inputs that failed, and why", 3)
    page.table(problems)


def checks_section(page: Page, checks: pd.DataFrame) -> None:
    page.heading("Thresholds and the previous run (categories.csv)")
    page.table(checks, digits=4, status=True)


def completion_section(page: Page, parts: pd.DataFrame) -> None:
    page.heading("Shape completion")
    if parts.empty:
        page.text("no completion scores in this run", "nodata")
        return
    categories = category_means(parts, HELD_OUT)
    page.text("Held-out parts, one view. Observed protocol: the networks see the observed "
              "points and the camera only; oracle-box: the paper's setting (truth grid), "
              "beside it for comparison.")
    page.heading("IoU (%) per category beside the paper's Table II", 3)
    page.table(paper_iou_table(categories), digits=1)
    page.heading("Projection overlap XY/YZ/ZX (%) beside the paper's Table I", 3)
    page.table(paper_overlap_table(categories))
    page.heading("Every metric per category, method and protocol", 3)
    page.table(categories)
    page.plot("category_iou", "IoU per category and method (observed)",
              lambda fig: _bars(fig, categories[categories["protocol"] == "observed"]))
    page.plot("iou_by_view_angle", "IoU against the view angle (observed, all categories)",
              lambda fig: _lines(fig, iou_by_view_angle(parts), "view azimuth (degrees)"))
    page.plot("iou_by_n_views", "IoU against the number of views (observed, all categories)",
              lambda fig: _lines(fig, iou_by_n_views(parts), "views"))


def _bars(fig: Any, table: pd.DataFrame) -> bool:
    if table.empty:
        return False
    wide = table.pivot_table(index="category", columns="method", values="iou")
    wide.plot.bar(ax=fig.add_subplot(1, 1, 1), rot=0, ylabel="IoU", ylim=(0, 1))
    return True


def _lines(fig: Any, table: pd.DataFrame, xlabel: str) -> bool:
    rows = table[(table["protocol"] == "observed") & (table["category"] == "all")]
    if rows.empty:
        return False
    ax = fig.add_subplot(1, 1, 1)
    columns = [c for c in rows.columns if c not in ("protocol", "category", "method")]
    for row in rows.to_dict("records"):
        ax.plot(columns, [row[c] for c in columns], marker="o", label=row["method"])
    ax.set(xlabel=xlabel, ylabel="IoU", ylim=(0, 1))
    ax.legend()
    return True


def relations_section(page: Page, summary: pd.DataFrame, pairs: pd.DataFrame) -> None:
    page.heading("Relations")
    if summary.empty:
        page.text("no relation scores in this run", "nodata")
        return
    page.heading("Accuracy (%) per relation, input and method beside the paper's Table III", 3)
    page.table(accuracy_table(summary).reset_index(), digits=1)
    alls = summary[summary["category"] == "all"]
    page.heading("Precision, recall and F1 per relation, input and method (all categories)", 3)
    page.table(alls[["input", "method", "relation", "n", "accuracy", "precision", "recall",
                     "f1", "violation_rate"]])
    if "confidence" in pairs:
        page.heading("Calibration of the confidences (%)", 3)
        page.table(calibration_table(pairs), digits=1)
    page.plot("relation_accuracy", "Accuracy per relation by input (ltn)",
              lambda fig: _relation_bars(fig, alls))
    page.plot("confusion", "Confusion matrices of ltn on completed points, per relation",
              lambda fig: _confusion(fig, pairs))


def _relation_bars(fig: Any, alls: pd.DataFrame) -> bool:
    rows = alls[alls["method"] == "ltn"]
    if rows.empty:
        return False
    wide = rows.pivot_table(index="relation", columns="input", values="accuracy")
    wide = wide.reindex([r for r in RELATIONS if r in wide.index])
    wide.plot.bar(ax=fig.add_subplot(1, 1, 1), rot=30, ylabel="accuracy", ylim=(0, 1))
    return True


def _confusion(fig: Any, pairs: pd.DataFrame) -> bool:
    rows = pairs[(pairs["method"] == "ltn") & (pairs["input"] == "completed")] \
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
        for (i, j), v in pd.DataFrame(counts).stack().items():
            ax.text(j, i, str(v), ha="center", va="center", fontsize=8,
                    color="white" if v > counts.max() / 2 else "black")
        ax.set(title=relation, xticks=[0, 1], yticks=[0, 1], xticklabels=["no", "yes"],
               yticklabels=["no", "yes"], xlabel="predicted", ylabel="truth")
    return True


def assemblies_section(page: Page, mates: pd.DataFrame, joints: pd.DataFrame) -> None:
    page.heading("Assemblies against their CAD mates")
    page.text("ltn on completed points against the relations and joints of the CAD.")
    page.table(mates)
    page.heading("Joint type: CAD (rows) against predicted (columns)", 3)
    if joints.empty:
        page.text("no jointed pairs in this run", "nodata")
        return
    agree = float(joints["agree"].mean())
    page.text(f"{len(joints)} jointed pair views, {100 * agree:.1f}% agree.")
    page.table(pd.crosstab(joints["cad_joint"], joints["predicted_joint"]).reset_index())


def trends_section(page: Page, history: Sequence[tuple[str, pd.DataFrame]]) -> None:
    page.heading("Trends over the last runs")
    metrics = ("completion_iou", "relation_accuracy", "mates_f1", "ingest_ok_fraction")
    page.plot("trends", "Headline metrics (all categories) over the last runs",
              lambda fig: _trends(fig, history, metrics))


def _trends(fig: Any, history: Sequence[tuple[str, pd.DataFrame]],
            metrics: Sequence[str]) -> bool:
    ax = fig.add_subplot(1, 1, 1)
    labels = [run_id[:15] for run_id, _ in history]
    drawn = False
    for metric in metrics:
        values = [_value(table, metric) for _, table in history]
        if any(v == v for v in values):  # some value that is not NaN
            ax.plot(labels, values, marker="o", label=metric)
            drawn = True
    ax.set(xlabel="run", ylabel="value", ylim=(0, 1.05))
    ax.tick_params(axis="x", labelrotation=20)
    if drawn:
        ax.legend()
    return drawn


def _value(table: pd.DataFrame, metric: str) -> float:
    rows = table[(table["metric"] == metric) & (table["category"] == "all")]
    return float(rows["value"].iloc[0]) if len(rows) else float("nan")
