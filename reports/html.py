"""``report.html``: one self-contained page per run (plots inline as PNG), read the next morning.

The first screen is the verdict: pass or fail, per category the headline metrics with their
threshold and the previous night's value, and the three plots a QA engineer looks at first
(completion IoU per category and method, relation F1 against the CAD per relation, joint
agreement). The long tables follow, each folded in a ``<details>`` with links to the run
files it comes from: the inputs that failed, the run's facts, the threshold checks, completion
beside the paper's Tables I and II, relations beside Table III, the assemblies against their
CAD mates and joints, the trends over earlier runs. Every plot is an ``img`` with a
``data-plot`` name; a section without data says so instead. Every string from the input
(names, paths, reasons) is HTML-escaped. matplotlib is imported only when a plot is drawn, so
that ``reports`` imports fast.
"""

from __future__ import annotations

import base64
import html
import io
import math
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from reports import plots
from reports.completion import (
    iou_by_n_views,
    iou_by_view_angle,
    labelled_methods,
    paper_iou_table,
    paper_overlap_table,
)
from reports.headline import HEADLINE_NOTE, display_table
from reports.relations import accuracy_table, calibration_table
from reports.verdict import HEADLINE, LABELS, Figure, Verdict

FIRST_SCREEN = ("category_iou", "relation_f1", "joint_agreement")
PLOTS = (*FIRST_SCREEN, "iou_by_view_angle", "iou_by_n_views", "relation_accuracy",
         "confusion", "trends")
WIDE, SMALL = (11.0, 4.2), (5.4, 3.6)  # figure sizes, inches: a folded section's, the first's
STYLE = """
body{font-family:system-ui,sans-serif;margin:1.5em 2em;max-width:1300px;color:#222}
h1{margin:0 0 4px;font-size:1.6em}h2{display:inline;font-size:1.25em}
summary{cursor:pointer;border-bottom:2px solid #ccc;padding:6px 0;margin-top:1em}
.files{font-size:13px;margin-left:1em;color:#555}.files a{margin-right:0.6em}
table{border-collapse:collapse;margin:0.5em 0 1em;font-size:13px}
th,td{border:1px solid #ccc;padding:3px 7px;text-align:right}th{background:#f2f2f2}
td:first-child,th:first-child{text-align:left}
.pass{background:#d9f2d9}.fail,.regressed{background:#f8d0d0}.too-few,.no-data,
.no-threshold{background:#eee;color:#666}.nodata{color:#888;font-style:italic}
table.verdict{font-size:14px}
table.verdict td,table.verdict th{text-align:left;white-space:nowrap}
table.verdict th{white-space:normal;vertical-align:bottom}
table.verdict small{color:#555}
.facts,.legend{font-size:13px;color:#555;margin:2px 0 6px}
.banner{padding:8px;font-weight:bold;margin:6px 0}
img{max-width:100%;border:1px solid #ddd}figure{margin:0.5em 0}
figcaption{font-size:13px;color:#444}
.first{display:flex;gap:12px}.first figure{flex:1;min-width:0;margin:0}
.first img{width:100%}
"""


class Page:
    """An HTML page built section by section."""

    def __init__(self, title: str) -> None:
        self.parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
                      f"<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>",
                      f"<h1>{html.escape(title)}</h1>"]

    def heading(self, text: str, level: int = 3) -> None:
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

    def plot(self, name: str, alt: str, draw: Callable[[Any], bool],
             size: tuple[float, float] = WIDE) -> None:
        """``draw(figure)`` fills a matplotlib figure and says whether it had data."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        # Labels are category and file names from input: "$" in one is text, not mathtext
        # (which fails on what it cannot parse).
        with matplotlib.rc_context({"text.parse_math": False}):
            fig = plt.figure(figsize=size)
            try:
                if not draw(fig):
                    self.parts.append(f"<figure><p class='nodata'>{html.escape(alt)}: no data"
                                      "</p></figure>")
                    return
                buf = io.BytesIO()
                fig.tight_layout()
                fig.savefig(buf, format="png", dpi=100 if size == SMALL else 80)
            finally:
                plt.close(fig)
        data = base64.b64encode(buf.getvalue()).decode()
        self.parts.append(f"<figure><img data-plot='{name}' alt='{html.escape(alt)}' "
                          f"src='data:image/png;base64,{data}'>"
                          f"<figcaption>{html.escape(alt)}</figcaption></figure>")

    @contextmanager
    def folded(self, title: str, files: Sequence[str] = ()) -> Iterator[None]:
        """A ``<details>`` section, closed, titled, with links to the run files it shows."""
        links = "".join(f"<a href='{html.escape(f)}'>{html.escape(f)}</a>" for f in files)
        self.parts.append(f"<details><summary><h2>{html.escape(title)}</h2>"
                          f"<span class='files'>{links}</span></summary>")
        yield
        self.parts.append("</details>")

    def render(self) -> str:
        return "\n".join([*self.parts, "</body></html>"])


# ---------------------------------------------------------------- the first screen


def first_screen(page: Page, verdict: Verdict, facts: str, categories: pd.DataFrame,
                 mates: pd.DataFrame, joints: pd.DataFrame, intervals: str = "",
                 said: Sequence[str] = ()) -> None:
    """The verdict, its table of headline figures, the assembly figures' intervals
    (``verdict.assembly_intervals``), the sentences ``said`` (the completion headline's
    interval, where the floors came from), the failed inputs' count and the three plots
    (``categories``: ``completion_categories`` rows of the observed protocol)."""
    page.text(facts, "facts")
    banner = {"PASS": "pass", "FAIL": "fail"}.get(verdict.word, "no-data")
    page.parts.append(f"<div class='banner {banner}'>{html.escape(verdict.headline())}</div>")
    page.parts.append(verdict_table(verdict))
    page.text("Each cell: tonight's value, its floor and the previous night's value. Red: below "
              "the floor (fail) or worse than the previous night by more than the allowed drop "
              "(regressed); grey: too few parts, pairs or files to check. A category's verdict "
              "is the worst of all its checks (the folded table below lists every one).",
              "legend")
    for line in said:
        page.text(f"{line}.", "legend")
    if intervals:
        page.text(f"Assemblies: {intervals}.", "legend")
    if verdict.problems:
        page.text(f"Inputs that failed: {verdict.problem_counts()}; files and reasons in "
                  "\"Inputs that failed, and why\" below.", "legend")
    page.parts.append("<div class='first'>")
    page.plot("category_iou", "Completion IoU per category and method (held-out parts, one "
              "view, observed protocol, per-part mean over every context)",
              lambda fig: plots.category_iou(fig, labelled_methods(categories)), SMALL)
    page.plot("relation_f1", "Relation F1 against the CAD per relation, every assembly "
              "(ltn on completed points; n: the CAD's pairs)",
              lambda fig: plots.relation_f1(fig, mates), SMALL)
    page.plot("joint_agreement", "Joint agreement: the product's joint against the CAD's",
              lambda fig: plots.joint_agreement(fig, joints), SMALL)
    page.parts.append("</div>")


def as_built_screen(page: Page, run_dir: Path) -> None:
    """Each assembly as built against its design: its verdict (holds, the broken mates, or not
    inspectable) and its first view coloured by the scan's distance from the registered CAD,
    with the histogram and the share within tolerance."""
    from reports.asbuilt import verdicts

    path = run_dir / "as_built.csv"
    if not path.is_file():
        return
    table = pd.read_csv(path)
    if table.empty:
        return
    page.heading("As built against as designed", 3)
    page.table(verdicts(table))
    for image in sorted(run_dir.glob("deviation-*.npz")):
        with np.load(image) as z:
            data, tol = z["deviation_mm"], float(z["tolerance_mm"])
        assembly = image.stem.removeprefix("deviation-")
        page.plot(f"deviation-{assembly}", f"{assembly}: scan to CAD, first view",
                  _deviation_plot(data, tol, assembly), WIDE)


def _deviation_plot(data: np.ndarray, tolerance_mm: float, title: str
                    ) -> Callable[[Any], bool]:
    def draw(fig: Any) -> bool:
        return plots.deviation(fig, data, tolerance_mm, title)
    return draw


def inspection_section(page: Page, run_dir: Path) -> None:
    """The inspection's own figures: defects caught, false alarms, pose errors, and the
    registered relations' F1 beside the truth's."""
    for name in ("inspect_summary.csv", "inspect_pose_summary.csv", "registered_mates.csv"):
        path = run_dir / name
        if path.is_file():
            page.heading(name.removesuffix(".csv").replace("_", " "), 4)
            page.table(pd.read_csv(path), digits=3)


def verdict_table(verdict: Verdict) -> str:
    """Per category (rows) its verdict and headline figures (columns), coloured by status."""
    head = "".join(f"<th>{html.escape(LABELS[m])}</th>" for m in HEADLINE)
    rows = [f"<table class='verdict' id='verdict'><tr><th>category</th><th>verdict</th>{head}"
            "</tr>"]
    for c in verdict.categories:
        checks = f"{c.checked} check{'s' if c.checked != 1 else ''}"
        count = (f"{c.failed} of {checks} failed" if c.failed else
                 f"{checks} passed" if c.checked else "no check applied")
        cells = "".join(_figure_cell(c.figure(m)) for m in HEADLINE)
        rows.append(f"<tr><td>{html.escape(c.category)}</td>"
                    f"<td class='{html.escape(c.status)}'><b>{html.escape(c.status)}</b><br>"
                    f"<small>{count}</small></td>"
                    f"{cells}</tr>")
    if not verdict.categories:
        rows.append(f"<tr><td colspan='{len(HEADLINE) + 2}' class='nodata'>no metrics in this "
                    "run</td></tr>")
    return "".join(rows) + "</table>"


def _figure_cell(figure: Figure | None) -> str:
    """The value and its status on the first line; floor and previous value below."""
    if figure is None:
        return "<td>-</td>"
    value = "-" if math.isnan(figure.value) else f"{figure.value:.3f}"
    status = "" if figure.status in ("pass", "no-threshold") else figure.status
    if figure.status == "too-few":
        status = f"too few (n={figure.n})"
    notes = [f"{label} {v:.3f}" for label, v in (("floor", figure.threshold),
                                                  ("prev", figure.previous)) if not math.isnan(v)]
    return (f"<td class='{html.escape(figure.status)}'><b>{value}</b> {html.escape(status)}"
            f"<br><small>{' · '.join(notes) or '&nbsp;'}</small></td>")


# ---------------------------------------------------------------- the folded sections


def completion_section(page: Page, parts: pd.DataFrame, categories: pd.DataFrame,
                       headline: pd.DataFrame | None = None) -> None:
    """``categories``: ``completion_categories`` rows of both protocols (held-out parts);
    ``headline``: ``completion_headline.csv`` (``reports.headline``)."""
    if parts.empty:
        page.text("no completion scores in this run", "nodata")
        return
    if headline is not None and len(headline):
        page.heading("The headline: IoU (%) per distinct shape, parts scored where they were "
                     "placed (observed protocol)")
        page.text(HEADLINE_NOTE)
        page.table(display_table(headline))
        page.text("The tables below are per-part means over every context (parts re-rendered "
                  "alone too), as the paper's are.")
    page.text("Held-out parts, one view. Observed protocol: the networks see the observed "
              "points and the camera only; oracle-box: the paper's setting (truth grid), "
              "beside it for comparison.")
    page.heading("IoU (%) per category beside the paper's Table II")
    page.table(paper_iou_table(categories), digits=1)
    page.heading("Projection overlap XY/YZ/ZX (%) beside the paper's Table I")
    page.table(paper_overlap_table(categories))
    page.heading("Every metric per category, method and protocol")
    page.table(labelled_methods(categories))
    page.plot("iou_by_view_angle", "IoU against the view angle (observed, all categories)",
              lambda fig: plots.iou_lines(fig, iou_by_view_angle(parts), "view azimuth "
                                          "(degrees)"))
    page.plot("iou_by_n_views", "IoU against the number of views (observed, all categories)",
              lambda fig: plots.iou_lines(fig, iou_by_n_views(parts), "views"))


def relations_section(page: Page, summary: pd.DataFrame, pairs: pd.DataFrame) -> None:
    if summary.empty:
        page.text("no relation scores in this run", "nodata")
        return
    page.heading("Accuracy (%) per relation, input and method beside the paper's Table III")
    page.table(accuracy_table(summary).reset_index(), digits=1)
    alls = summary[summary["category"] == "all"]
    page.heading("Precision, recall and F1 per relation, input and method (all categories)")
    page.table(alls[["input", "method", "relation", "n", "accuracy", "precision", "recall",
                     "f1", "violation_rate"]])
    if "confidence" in pairs:
        page.heading("Calibration of the confidences (%)")
        page.table(calibration_table(pairs), digits=1)
    page.plot("relation_accuracy", "Accuracy per relation by input (ltn)",
              lambda fig: plots.relation_accuracy(fig, alls))
    page.plot("confusion", "Confusion matrices of ltn on completed points, per relation",
              lambda fig: plots.confusion(fig, pairs))


def assemblies_section(page: Page, mates: pd.DataFrame, joints: pd.DataFrame) -> None:
    page.text("ltn on completed points against the relations and joints of the CAD.")
    page.table(mates)
    page.heading("Joint type: CAD (rows) against predicted (columns)")
    if joints.empty:
        page.text("no jointed pairs in this run", "nodata")
        return
    agree = float(joints["agree"].mean())
    page.text(f"{len(joints)} jointed pair views, {100 * agree:.1f}% agree.")
    page.table(pd.crosstab(joints["cad_joint"], joints["predicted_joint"]).reset_index())


def trends_section(page: Page, history: Sequence[tuple[str, pd.DataFrame]]) -> None:
    metrics = ("completion_iou_shapes", "completion_iou", "relation_accuracy", "mates_f1",
               "ingest_ok_fraction")
    page.plot("trends", "Headline metrics (all categories) over the last runs",
              lambda fig: plots.trends(fig, history, metrics))
