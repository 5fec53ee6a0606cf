"""The as-built report: each assembly's verdict, each CAD mate as built, and how well the
inspection does on planted defects, with pandas only.

Files other tools read (their names and columns are a contract):

- ``as_built.csv`` (and ``.parquet``): one row per CAD face mate of each assembly as built
  (its intact capture, every view): ``AS_BUILT_COLUMNS`` (the mates stage's keys: index_a,
  index_b, face_a, face_b, relation; the status: holds / broken / not observable / not
  inspectable; why; the residuals in the directions the mate constrains with their
  thresholds), then the two parts' ids;
- ``inspect_summary.csv``: per set of views (``all``, or one view alone) and method (the
  product ``registered``, the ``design`` baseline): the share of the planted defects caught per
  kind and size, and the false alarms on the intact assemblies per part and per mate;
- ``inspect_poses.csv``: each registered part's pose error against where it stood (the least
  over its symmetries), per route (``design``: refined from the aligned design; ``search``:
  found without it), with the share of its surface in view; ``inspect_pose_summary.csv`` their
  median and 90th percentile;
- ``registered_mates.csv``: F1 against the CAD's face mates per relation of every method on the
  ``registered`` input (the CAD at the poses the search route found) and on ``truth`` (the CAD
  where the parts stood), on the same pair views: all of them, and those where both parts show
  at least ``VISIBLE`` of their surface;
- ``inspect.md``: all of it in Markdown;
- a JUnit test suite per assembly (``junit_suites``, in the run's ``junit.xml``): a test case
  per CAD mate as built, a failure where it is broken, skipped where it could not be judged.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from cadio.inspect.asbuilt import verdict_of
from cadio.workspace import atomic_path
from reports.tables import markdown_table

AS_BUILT_COLUMNS = ("assembly", "index_a", "index_b", "face_a", "face_b", "relation",
                    "status", "reason", "axis_distance_mm", "axis_distance_mm_threshold",
                    "axis_angle_deg", "axis_angle_deg_threshold", "plane_offset_mm",
                    "plane_offset_mm_threshold", "normal_angle_deg",
                    "normal_angle_deg_threshold", "part_a", "part_b", "capture")
SUMMARY_COLUMNS = ("views", "method", "measure", "kind", "size", "n", "rate")
VISIBLE = 0.2  # both parts of a pair view show at least this share of their surface
INTACT, RECORDING, ALL_VIEWS, PRODUCT = "intact", "recording", "all", "registered"
TABLES = ("mates", "poses", "defects", "parts", "found", "shares")


def read_inspections(folders: Iterable[Path]) -> dict[str, pd.DataFrame]:
    """Every assembly's inspection rows (``cadio.inspect.evaluate``), table by table."""
    frames: dict[str, list[pd.DataFrame]] = {t: [] for t in TABLES}
    for folder in folders:
        for name in TABLES:
            path = Path(folder) / f"{name}.parquet"
            if path.is_file():
                frames[name].append(pd.read_parquet(path))
    return {t: pd.concat(f, ignore_index=True) if f else pd.DataFrame()
            for t, f in frames.items()}


def as_built_frame(mates: pd.DataFrame) -> pd.DataFrame:
    """The product's answer: each CAD mate of each intact assembly as built, every view."""
    cols = list(AS_BUILT_COLUMNS)
    if mates.empty:
        return pd.DataFrame(columns=cols)
    rows = mates[mates["variant"].isin([INTACT, RECORDING]) & (mates["views"] == ALL_VIEWS)
                 & (mates["method"] == PRODUCT)]
    return rows.reindex(columns=cols).sort_values(
        ["assembly", "capture", "index_a", "index_b", "relation", "face_a", "face_b"]
    ).reset_index(drop=True)


def verdicts(as_built: pd.DataFrame) -> pd.DataFrame:
    """Per assembly: ``holds``, ``N mates broken`` (naming them) or ``not inspectable``, and
    the count of mates per status."""
    rows = []
    keys = ["assembly", "capture"] if "capture" in as_built else ["assembly"]
    for key, group in as_built.groupby(keys, sort=True, dropna=False):
        assembly, capture = (key[0], key[1]) if len(keys) == 2 else (key[0], "")
        counts = group["status"].value_counts()
        broken = group[group["status"] == "broken"]
        verdict = verdict_of(group["status"].tolist())
        which = "; ".join(f"{r.relation} {r.part_a[:8]}/{r.face_a} - {r.part_b[:8]}/{r.face_b}"
                          for r in broken.head(5).itertuples())
        rows.append({"assembly": assembly, "capture": capture, "verdict": verdict,
                     "broken": which,
                     **{s: int(counts.get(s, 0)) for s in ("holds", "not observable",
                                                           "not inspectable")}})
    return pd.DataFrame(rows, columns=["assembly", "capture", "verdict", "broken", "holds",
                                       "not observable", "not inspectable"])


def summary_frame(tables: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """Detection per defect kind and size, false alarms per part and per mate (intact)."""
    rows: list[dict[str, object]] = []
    defects = tables["defects"]
    if not defects.empty:
        for (views, method, kind, size), g in defects.groupby(["views", "method", "kind",
                                                                "size"], sort=True):
            rows.append({"views": views, "method": method, "measure": "caught", "kind": kind,
                         "size": float(size), "n": len(g), "rate": float(g["caught"].mean())})
    parts = tables["parts"]
    if not parts.empty:
        clean = parts[(parts["variant"] == INTACT) & parts["inspectable"]]
        for (views, method), g in clean.groupby(["views", "method"], sort=True):
            rows.append({"views": views, "method": method, "measure": "false alarm, parts",
                         "kind": "", "size": np.nan, "n": len(g),
                         "rate": float(g["flagged"].mean())})
    mates = tables["mates"]
    if not mates.empty:
        clean = mates[(mates["variant"] == INTACT) & (mates["status"] != "not inspectable")]
        for (views, method), g in clean.groupby(["views", "method"], sort=True):
            rows.append({"views": views, "method": method, "measure": "false alarm, mates",
                         "kind": "", "size": np.nan, "n": len(g),
                         "rate": float((g["status"] == "broken").mean())})
    return pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))


def pose_summary(poses: pd.DataFrame) -> pd.DataFrame:
    """Per set of views and route: parts, median and 90th percentile of the pose errors, and
    the share of parts given their own name (the search names copies of a shape by where they
    lie together: a ring of balls or a symmetric joint leaves which is which open)."""
    if poses.empty:
        return pd.DataFrame(columns=["views", "route", "n", "median_mm", "p90_mm",
                                     "median_deg", "p90_deg", "named"])
    g = poses.groupby(["views", "route"], sort=True)
    return pd.DataFrame({"n": g.size(),
                         "median_mm": g["error_mm"].median(), "p90_mm": g["error_mm"].quantile(0.9),
                         "median_deg": g["error_deg"].median(),
                         "p90_deg": g["error_deg"].quantile(0.9),
                         "named": g["named"].mean()}).reset_index()


def registered_f1(relations: pd.DataFrame, shares: pd.DataFrame) -> pd.DataFrame:
    """F1 against the CAD per input, method and relation over the inspection's pair views:
    every view (``visible`` all), and those whose two parts each show ``VISIBLE`` of their
    surface (``visible`` >= 0.2)."""
    cols = ["visible", "input", "method", "relation", "n", "n_cad", "f1"]
    if relations.empty:
        return pd.DataFrame(columns=cols)
    rel = relations.copy()
    rel["views"] = rel["scene"].astype(str).str.rsplit("@", n=1).str[1].fillna(ALL_VIEWS)
    rel["capture"] = rel["scene"].astype(str).str.rsplit("@", n=1).str[0]
    seen = shares[["capture", "views", "part_id", "visible_share"]] if not shares.empty else \
        pd.DataFrame(columns=["capture", "views", "part_id", "visible_share"])
    for side in ("a", "b"):
        rel = rel.merge(seen.rename(columns={"part_id": f"part_{side}",
                                             "visible_share": f"share_{side}"}),
                        on=["capture", "views", f"part_{side}"], how="left")
    rel["both_visible"] = (rel["share_a"] >= VISIBLE) & (rel["share_b"] >= VISIBLE)
    rows = []
    for label, subset in (("all", rel), (f">= {VISIBLE:g}", rel[rel["both_visible"]])):
        for (given, method, relation), g in subset.groupby(["input", "method", "relation"]):
            t, p = g["truth"].astype(bool), g["predicted"].astype(bool)
            tp, fp, fn = int((t & p).sum()), int((~t & p).sum()), int((t & ~p).sum())
            f1 = 2 * tp / (2 * tp + fp + fn) if (2 * tp + fp + fn) else np.nan
            rows.append({"visible": label, "input": given, "method": method,
                         "relation": relation, "n": len(g), "n_cad": int(t.sum()), "f1": f1})
    return pd.DataFrame(rows, columns=cols)


def inspection_markdown(as_built: pd.DataFrame, summary: pd.DataFrame, poses: pd.DataFrame,
                        f1: pd.DataFrame, failed: Sequence[str]) -> str:
    """``inspect.md``: verdicts, the defects caught, the false alarms, the pose errors and the
    registered relations' F1 beside the truth's."""
    lines = ["# As built against as designed", ""]
    if not as_built.empty:
        lines += ["## Verdict per assembly (every view of its intact capture)", "",
                  markdown_table(verdicts(as_built)), ""]
    if not summary.empty:
        caught = summary[summary["measure"] == "caught"].pivot_table(
            index=["kind", "size"], columns=["views", "method"], values="rate").reset_index()
        lines += ["## Planted defects caught (share)", "", markdown_table(caught.round(3)), "",
                  "## False alarms on the intact assemblies", "",
                  markdown_table(summary[summary["measure"] != "caught"].drop(
                      columns=["kind", "size"]).round(4)), ""]
    if not poses.empty:
        lines += ["## Pose errors (least over each part's symmetries)", "",
                  markdown_table(pose_summary(poses).round(3)), ""]
    if not f1.empty:
        wide = f1.pivot_table(index="relation", columns=["visible", "input", "method"],
                              values="f1").round(3).reset_index()
        lines += ["## F1 against the CAD's mates: registered beside truth, same pair views", "",
                  markdown_table(wide), ""]
    lines += [f"- {f}" for f in failed]
    return "\n".join(lines) + "\n"


def write_inspection_report(run_dir: Path, folders: Iterable[Path], relations: Iterable[Path],
                            failed: Sequence[str] = ()) -> Path:
    """Every as-built file of the run; returns ``inspect.md``'s path."""
    run_dir = Path(run_dir)
    folders = [Path(f) for f in folders]
    tables = read_inspections(folders)
    for image in (i for f in folders for i in f.glob("deviation-*.npz")):
        with atomic_path(run_dir / image.name) as tmp:
            tmp.write_bytes(image.read_bytes())
    rel = [pd.read_parquet(p) for p in relations if Path(p).is_file()]
    relation_rows = pd.concat(rel, ignore_index=True) if rel else pd.DataFrame()
    as_built = as_built_frame(tables["mates"])
    summary = summary_frame(tables)
    f1 = registered_f1(relation_rows, tables["shares"])
    outputs = {"as_built.csv": as_built, "inspect_summary.csv": summary,
               "inspect_poses.csv": tables["poses"],
               "inspect_pose_summary.csv": pose_summary(tables["poses"]),
               "inspect_defects.csv": tables["defects"], "registered_mates.csv": f1}
    for name, frame in outputs.items():
        with atomic_path(run_dir / name) as tmp:
            frame.to_csv(tmp, index=False)
    with atomic_path(run_dir / "as_built.parquet") as tmp:
        as_built.to_parquet(tmp, index=False)
    with atomic_path(run_dir / "inspect_mates.parquet") as tmp:
        tables["mates"].to_parquet(tmp, index=False)
    md = run_dir / "inspect.md"
    with atomic_path(md) as tmp:
        tmp.write_text(inspection_markdown(as_built, summary, tables["poses"], f1, failed))
    return md


def junit_suites(as_built: pd.DataFrame) -> list[ET.Element]:
    """One JUnit test suite per assembly of ``as_built.csv``: a test case per CAD mate (class:
    the assembly; name: relation, part/face and part/face), a failure where it is broken with
    its residuals, skipped where it is not observable or not inspectable."""
    from reports.trends import xml_safe

    out = []
    keys = ["assembly", "capture"] if "capture" in as_built else ["assembly"]
    for key, rows in as_built.groupby(keys, sort=True, dropna=False):
        assembly, capture = key[0], (key[1] if len(keys) == 2 else "")
        broken = int((rows["status"] == "broken").sum())
        unjudged = int(rows["status"].isin(["not observable", "not inspectable"]).sum())
        suite = ET.Element("testsuite", name=xml_safe(f"as built {assembly} {capture}".strip()),
                           tests=str(len(rows)), failures=str(broken), errors="0",
                           skipped=str(unjudged))
        for r in rows.to_dict("records"):
            name = (f"{r['relation']} {r['index_a']}/{r['face_a']}-"
                    f"{r['index_b']}/{r['face_b']}")
            case = ET.SubElement(suite, "testcase", classname=xml_safe(assembly),
                                 name=xml_safe(name))
            said = _residual_text(r) or str(r.get("reason", ""))
            if r["status"] == "broken":
                ET.SubElement(case, "failure", type="broken", message=said).text = said
            elif r["status"] != "holds":
                ET.SubElement(case, "skipped", message=f"{r['status']}: {said}")
        out.append(suite)
    return out


def _residual_text(row: dict[str, object]) -> str:
    """A mate's residuals against their thresholds, in words."""
    parts = []
    for name in ("axis_distance_mm", "axis_angle_deg", "plane_offset_mm", "normal_angle_deg"):
        value, limit = row.get(name), row.get(f"{name}_threshold")
        if isinstance(value, float) and np.isfinite(value) and isinstance(limit, float):
            parts.append(f"{name} {value:.3g} (threshold {limit:.3g})")
    return "; ".join(parts)
