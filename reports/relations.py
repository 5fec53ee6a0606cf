"""The relation report: per-pair predictions, per-relation scores, and agreement with the CAD.

Three files other tools read (names and columns are a contract, DESIGN.md):

- ``relations_pairs.parquet``: one row per pair view x input x method x relation (``PAIR_COLUMNS``,
  plus ``violation``: the method's raw outputs broke an axiom that involves the relation, and
  ``joint``: the joint the method answers for the pair view, the same on its ten rows);
- ``relations_summary.csv``: input x method x relation x category (``all`` too) over the pairs
  clear of every tolerance boundary (``SUMMARY_COLUMNS``); ``relations_near_boundary.csv``
  holds the same scores over the near-boundary pairs, reported apart;
- ``assembly_mates.csv``: per assembly (and ``all``) and relation, the product method's
  predictions on the assemblies' captures against the CAD (``ASSEMBLY_COLUMNS``).

``relations.md`` puts the accuracies beside the paper's Table III. Plain pandas: no CAD, no torch.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from cadio.truth.joints import predicted_joint
from cadio.workspace import atomic_path, atomic_write
from reports.intervals import f1_interval, joint_interval
from reports.methods import product
from reports.tables import markdown_table

PAIR_COLUMNS = ("scene", "view", "part_a", "part_b", "category", "input", "method", "relation",
                "truth", "predicted", "confidence", "near_boundary")
SUMMARY_COLUMNS = ("input", "method", "relation", "category", "n", "accuracy", "precision",
                   "recall", "f1", "violation_rate")
# f1_low, f1_high: a 95% interval of f1 that resamples the distinct pairs (``f1_interval``)
ASSEMBLY_COLUMNS = ("assembly", "relation", "n_cad", "n_pred", "precision", "recall", "f1",
                    "pairs", "f1_low", "f1_high")
JOINT_COLUMNS = ("assembly", "view", "part_a", "part_b", "cad_joint", "predicted_joint", "agree")
RELATIONS = ("left", "right", "above", "below", "front", "behind", "parallel", "perpendicular",
             "concentric", "coincident")
# Table III of the paper: its accuracies (%) and those it quotes for RANSEM and CPN.
PAPER_TABLE_III = {
    "left": (99.7, 86.8, 79.0), "right": (99.5, 88.9, 79.0), "above": (99.6, None, 82.0),
    "below": (99.4, None, 79.0), "front": (99.5, None, None), "behind": (99.5, None, None),
    "coincident": (99.3, None, None), "parallel": (99.7, None, None),
    "perpendicular": (99.4, None, None), "concentric": (99.1, None, None),
}


def pairs_frame(rows: Iterable[dict[str, Any]]) -> pd.DataFrame:
    """The ``relations_pairs`` table from row dicts (missing ``violation`` is False, a missing
    ``joint`` is "": read from the concentric and coincident answers where it is scored)."""
    df = pd.DataFrame(list(rows), columns=[*PAIR_COLUMNS, "violation", "joint"])
    df["violation"] = df["violation"].fillna(False).astype(bool)
    df["joint"] = df["joint"].astype(object).fillna("").astype(str)
    for col in ("truth", "predicted", "near_boundary"):
        df[col] = df[col].astype(bool)
    df["view"] = df["view"].astype("int64")
    df["confidence"] = df["confidence"].astype("float64")
    return df


def scores(truth: np.ndarray, predicted: np.ndarray) -> dict[str, float]:
    """n, accuracy, precision, recall and F1 of boolean predictions (NaN where undefined)."""
    t, p = np.asarray(truth, dtype=bool), np.asarray(predicted, dtype=bool)
    tp, fp, fn = int(np.sum(t & p)), int(np.sum(~t & p)), int(np.sum(t & ~p))
    precision = tp / (tp + fp) if tp + fp else math.nan
    recall = tp / (tp + fn) if tp + fn else math.nan
    f1 = 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else math.nan
    accuracy = float(np.mean(t == p)) if len(t) else math.nan
    return {"n": len(t), "accuracy": accuracy, "precision": precision, "recall": recall,
            "f1": f1}


def summary_frame(pairs: pd.DataFrame) -> pd.DataFrame:
    """``relations_summary`` rows: input x method x relation x category, and category "all"."""
    rows = []
    for (inp, method, rel), group in pairs.groupby(["input", "method", "relation"], sort=True):
        parts = [("all", group), *group.groupby("category", sort=True)]
        for category, g in parts:
            rows.append({"input": inp, "method": method, "relation": rel, "category": category,
                         **scores(g["truth"].to_numpy(), g["predicted"].to_numpy()),
                         "violation_rate": float(g["violation"].mean()) if len(g) else math.nan})
    return pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))


def assembly_frame(pairs: pd.DataFrame, answers: tuple[str, str] | None = None) -> pd.DataFrame:
    """``assembly_mates`` rows: per assembly scene (and "all") and relation, the CAD's count
    (n_cad), the product method's (n_pred), their precision, recall and F1, and F1's 95%
    interval over the distinct pairs the views show (``f1_interval``)."""
    inp, method = answers or product()
    mine = pairs[(pairs["input"] == inp) & (pairs["method"] == method)]
    rows = []
    for assembly, group in [("all", mine), *mine.groupby("scene", sort=True)]:
        for rel in RELATIONS:
            g = group[group["relation"] == rel]
            s = scores(g["truth"].to_numpy(), g["predicted"].to_numpy())
            low, high, distinct = f1_interval(g)
            rows.append({"assembly": assembly, "relation": rel, "n_cad": int(g["truth"].sum()),
                         "n_pred": int(g["predicted"].sum()), "precision": s["precision"],
                         "recall": s["recall"], "f1": s["f1"], "pairs": distinct,
                         "f1_low": low, "f1_high": high})
    return pd.DataFrame(rows, columns=list(ASSEMBLY_COLUMNS))


def assembly_f1_table(pairs: pd.DataFrame) -> pd.DataFrame:
    """F1 against the CAD mates of every assembly pooled, per relation (rows) and input/method
    (columns): the product method beside every baseline on the same pair views."""
    rows = []
    for (inp, method, rel), g in pairs.groupby(["input", "method", "relation"], sort=True):
        rows.append({"relation": rel, "column": f"{inp}/{method}",
                     "f1": scores(g["truth"].to_numpy(), g["predicted"].to_numpy())["f1"]})
    if not rows:
        return pd.DataFrame()
    table = pd.DataFrame(rows).pivot(index="relation", columns="column", values="f1")
    return table.reindex([r for r in RELATIONS if r in table.index])


def joint_frame(pairs: pd.DataFrame, joints: pd.DataFrame,
                answers: tuple[str, str] | None = None) -> pd.DataFrame:
    """Joint-type agreement: for every view of an assembly pair whose CAD mates make a joint
    (``joints``: scene, part_a, part_b, kinematic), the product's joint (its joint head's
    answer; where a row has none, the joint its concentric and coincident answers imply)
    beside the CAD's kinematic joint (``JOINT_COLUMNS``)."""
    said = product_joints(pairs, answers)
    if said.empty or joints.empty:
        return pd.DataFrame(columns=list(JOINT_COLUMNS))
    both = pd.concat([joints, joints.rename(columns={"part_a": "part_b", "part_b": "part_a"})])
    merged = said.merge(both, on=["scene", "part_a", "part_b"])
    out = pd.DataFrame({
        "assembly": merged["scene"], "view": merged["view"], "part_a": merged["part_a"],
        "part_b": merged["part_b"], "cad_joint": merged["kinematic"],
        "predicted_joint": merged["predicted_joint"]})
    out["agree"] = out["cad_joint"] == out["predicted_joint"]
    return out[list(JOINT_COLUMNS)]


def product_joints(pairs: pd.DataFrame, answers: tuple[str, str] | None = None) -> pd.DataFrame:
    """The product's joint per pair view (scene, view, part_a, part_b, predicted_joint): its
    rows' ``joint``, or where they carry none, the one its concentric and coincident imply."""
    inp, method = answers or product()
    mine = pairs[(pairs["input"] == inp) & (pairs["method"] == method)
                 & pairs["relation"].isin(["concentric", "coincident"])]
    view = ["scene", "view", "part_a", "part_b"]
    if mine.empty:
        return pd.DataFrame(columns=[*view, "predicted_joint"])
    if "joint" not in mine.columns:
        mine = mine.assign(joint="")
    wide = mine.pivot_table(index=view, columns="relation", values="predicted",
                            aggfunc="first").reset_index()
    wide = wide.merge(mine.groupby(view)["joint"].first().reset_index(), on=view, how="left")
    no = pd.Series(False, index=wide.index)
    wide["predicted_joint"] = [
        j if isinstance(j, str) and j else predicted_joint(bool(c), bool(k))
        for c, k, j in zip(wide.get("concentric", no), wide.get("coincident", no),
                           wide["joint"], strict=True)]
    return wide[[*view, "predicted_joint"]]


def false_joints(pairs: pd.DataFrame, joints: pd.DataFrame,
                 answers: tuple[str, str] | None = None) -> tuple[int, int]:
    """(views of assembly pairs without a CAD joint, those the product gives a joint): the
    joint agreement's other side (it is scored on the jointed pairs only)."""
    said = product_joints(pairs, answers)
    said = said[said["scene"].astype(str).str.startswith("assembly-")]
    jointed = set()
    for r in joints.itertuples():
        jointed |= {(r.scene, r.part_a, r.part_b), (r.scene, r.part_b, r.part_a)}
    free = [j for s, a, b, j in zip(said["scene"], said["part_a"], said["part_b"],
                                    said["predicted_joint"], strict=True)
            if (s, a, b) not in jointed]
    return len(free), sum(j != "none" for j in free)


def accuracy_table(summary: pd.DataFrame) -> pd.DataFrame:
    """Accuracy (%) per relation (rows) and input/method (columns), category "all", with the
    paper's Table III beside it."""
    alls = summary[summary["category"] == "all"]
    table = alls.pivot_table(index="relation", columns=["input", "method"], values="accuracy")
    table.columns = [f"{i}/{m}" for i, m in table.columns]
    table = (100.0 * table).reindex([r for r in RELATIONS if r in table.index])
    for k, name in enumerate(("paper", "RANSEM", "CPN")):
        table[name] = [PAPER_TABLE_III[r][k] for r in table.index]
    return table


def expected_calibration_error(confidence: npt.ArrayLike, correct: npt.ArrayLike,
                               bins: int = 15) -> float:
    """ECE: sum over equal-width confidence bins of (share of items) |accuracy - mean confidence|.

    Args:
        confidence: any shape, in [0, 1]; correct: same shape, bool (or 0/1).

    Returns:
        The error in [0, 1]; NaN without items.

    Raises:
        ValueError: the two differ in shape.
    """
    conf = np.asarray(confidence, dtype=np.float64).ravel()
    hit = np.asarray(correct, dtype=np.float64).ravel()
    if conf.shape != hit.shape:
        raise ValueError("confidence and correct must be of one shape")
    if not conf.size:
        return math.nan
    which = np.minimum((conf * bins).astype(int), bins - 1)
    gap = np.bincount(which, hit - conf, minlength=bins)  # per bin: sum(correct - confidence)
    return float(np.abs(gap).sum() / conf.size)


def calibration_table(pairs: pd.DataFrame) -> pd.DataFrame:
    """ECE (%) of each learned input/method's confidences over all its answers."""
    rows = []
    learned = pairs[pairs["confidence"].notna()]
    for (inp, method), g in learned.groupby(["input", "method"], sort=True):
        correct = (g["truth"] == g["predicted"]).to_numpy()
        rows.append({"input": inp, "method": method, "answers": len(g),
                     "mean_confidence": 100 * float(g["confidence"].mean()),
                     "accuracy": 100 * float(correct.mean()),
                     "ece": 100 * expected_calibration_error(g["confidence"].to_numpy(),
                                                             correct)})
    return pd.DataFrame(rows)


def violation_table(summary: pd.DataFrame) -> pd.DataFrame:
    """Violation rate (%) per relation and input/method, category "all"."""
    alls = summary[summary["category"] == "all"]
    table = alls.pivot_table(index="relation", columns=["input", "method"],
                             values="violation_rate")
    table.columns = [f"{i}/{m}" for i, m in table.columns]
    return 100.0 * table.reindex([r for r in RELATIONS if r in table.index])


def relations_markdown(summary: pd.DataFrame, near: pd.DataFrame, assemblies: pd.DataFrame,
                       notes: Sequence[str] = (), joints: pd.DataFrame | None = None,
                       calibration: pd.DataFrame | None = None,
                       assembly_f1: pd.DataFrame | None = None,
                       false_joints: tuple[int, int] | None = None) -> str:
    """The Markdown report: accuracy beside Table III, violations, near-boundary, assemblies."""
    out = ["# Relations", *notes, "",
           "## Accuracy per relation (%, clear pairs), beside the paper's Table III", ""]
    out += [_markdown(accuracy_table(summary)) if len(summary) else "no pair scored", ""]
    out += ["## Violation rate of the raw outputs (%)", ""]
    out += [_markdown(violation_table(summary)) if len(summary) else "no pair scored", ""]
    if calibration is not None and len(calibration):
        out += ["## Calibration of the confidences (%, clear pairs)", "",
                markdown_table(calibration.round(2)), ""]
    out += ["## Near-boundary pairs: accuracy (%)", ""]
    out += [_markdown(accuracy_table(near).drop(columns=["paper", "RANSEM", "CPN"]))
            if len(near) else "no near-boundary pair", ""]
    given, method = product()
    out += [f"## Against the CAD mates of the assemblies ({method} on {given} inputs)",
            ""]
    out += [markdown_table(assemblies.round(3)) if len(assemblies) else "no assembly captured"]
    if len(assemblies):
        out += ["", "f1_low to f1_high: a 95% interval of f1 that resamples the distinct pairs "
                "(pairs), each with all its views."]
    if assembly_f1 is not None and len(assembly_f1):
        out += ["", "## F1 against the CAD mates, every method and input (all assemblies)", "",
                markdown_table(assembly_f1.round(3).reset_index())]
    if joints is not None and len(joints):
        agree = joints.groupby(["assembly", "cad_joint"]).agg(
            n=("agree", "size"), agreement=("agree", "mean")).reset_index()
        low, high, pairs = joint_interval(joints)
        out += ["", f"## Joint types: the CAD's beside {method}'s on {given} inputs",
                "", markdown_table(agree.round(3)), "",
                f"Joint agreement {joints['agree'].mean():.3f} over {len(joints)} views of "
                f"{pairs} distinct pairs; 95% interval {low:.3f} to {high:.3f}, resampling the "
                "pairs (the views of one pair are not independent)."]
    if false_joints is not None and false_joints[0]:
        n, claimed = false_joints
        out += ["", f"Of the {n} views of assembly pairs without a CAD joint, {claimed} "
                f"({claimed / n:.1%}) were given a joint."]
    return "\n".join(out) + "\n"



def _markdown(table: pd.DataFrame) -> str:
    return markdown_table(table.round(1).reset_index())


def write_relation_report(out: Path, pairs: pd.DataFrame, notes: Sequence[str] = (),
                          joints: pd.DataFrame | None = None) -> Path:
    """Write the relation files of a run folder, each atomically; the Markdown report's path."""
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "relations_pairs.parquet") as tmp:
        pairs.to_parquet(tmp, index=False)
    clear, near = pairs[~pairs["near_boundary"]], pairs[pairs["near_boundary"]]
    summary, near_summary = summary_frame(clear), summary_frame(near)
    in_assemblies = pairs[pairs["scene"].astype(str).str.startswith("assembly-")]
    assemblies = assembly_frame(in_assemblies)
    agreement = joint_frame(pairs, joints if joints is not None else pd.DataFrame())
    for name, frame in (("relations_summary.csv", summary),
                        ("relations_near_boundary.csv", near_summary),
                        ("assembly_mates.csv", assemblies), ("assembly_joints.csv", agreement)):
        with atomic_write(out / name, "w") as fh:
            frame.to_csv(fh, index=False)
    path = out / "relations.md"
    with atomic_write(path, "w") as fh:
        fh.write(relations_markdown(
            summary, near_summary, assemblies, notes, agreement, calibration_table(clear),
            assembly_f1_table(in_assemblies),
            false_joints(pairs, joints) if joints is not None and len(agreement) else None))
    return path


def combine_pairs(paths: Sequence[Path], joints: bool = False) -> pd.DataFrame:
    """The rows of several batch files in one table (``relations_pairs`` rows, or the CAD
    joints of the batches with ``joints``)."""
    frames = [pd.read_parquet(p) for p in paths if Path(p).exists()]
    if frames:
        return pd.concat(frames, ignore_index=True)
    return pd.DataFrame(columns=["scene", "part_a", "part_b", "kinematic"]) if joints else \
        pairs_frame([])
