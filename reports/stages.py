"""Per-category summaries of the ground-truth and capture stages, for the nightly report.

Pure pandas: inputs are the small per-item summaries the stages return, outputs are tables.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import pandas as pd

RELATIONS = ("left", "right", "above", "below", "front", "behind",
             "parallel", "perpendicular", "concentric", "coincident")


def mates_table(assemblies: Sequence[dict[str, Any]]) -> pd.DataFrame:
    """Per category: assemblies, parts, pairs, face mates, part relations, joints, failures.

    Args:
        assemblies: one dict per assembly with ``category``, ``status`` and, when ok, the
            counts ``n_parts``, ``n_pairs``, ``face_mates``, ``relations``, ``joints``.
    """
    columns = ["category", "assemblies", "failed", "parts", "pairs", "contact_pairs",
               "face_mates", "relations", "joints"]
    if not assemblies:
        return pd.DataFrame(columns=columns)
    frame = pd.DataFrame([{**{c: 0 for c in columns[3:]}, **a} for a in assemblies])
    ok = frame["status"] == "ok"
    grouped = frame.groupby("category", sort=True)
    table = pd.DataFrame({
        "assemblies": grouped.size(),
        "failed": grouped["status"].apply(lambda s: int((s != "ok").sum())),
    })
    for col, src in [("parts", "n_parts"), ("pairs", "n_pairs"),
                     ("contact_pairs", "n_contact_pairs"), ("face_mates", "face_mates"),
                     ("relations", "relations"), ("joints", "joints")]:
        values = frame[src] if src in frame else 0
        table[col] = frame.assign(v=values).loc[ok].groupby("category")["v"].sum()
    return table.fillna(0).astype(int).reset_index()[columns]


def joints_table(assemblies: Sequence[dict[str, Any]]) -> pd.DataFrame:
    """Joint types found, per category (suggested CAD joint names)."""
    rows = [{"category": a["category"], "joint": j, "count": n}
            for a in assemblies if a.get("status") == "ok"
            for j, n in a.get("joint_types", {}).items()]
    if not rows:
        return pd.DataFrame(columns=["category", "joint", "count"])
    return (pd.DataFrame(rows).groupby(["category", "joint"], sort=True)["count"].sum()
            .reset_index())


def scenes_table(scenes: pd.DataFrame) -> pd.DataFrame:
    """Scenes per split and intended relation, with the share where the intent holds."""
    if scenes.empty:
        return pd.DataFrame(columns=["split", "intended", "scenes", "holds"])
    holds = [bool(row[row["intended"]]) for row in scenes.to_dict("records")]
    table = (scenes.assign(holds=holds).groupby(["split", "intended"], sort=True)
             .agg(scenes=("scene_id", "count"), holds=("holds", "mean")).reset_index())
    table["holds"] = table["holds"].round(3)
    return table


def captures_table(captures: pd.DataFrame, scenes: pd.DataFrame) -> pd.DataFrame:
    """Per category: captures, frames and part views captured (a pair counts in both parts'
    categories), bytes on disk, failures."""
    columns = ["category", "captures", "frames", "part_views", "mbytes", "failed"]
    if captures.empty:
        return pd.DataFrame(columns=columns)
    merged = captures.merge(scenes[["scene_id", "category_a", "category_b"]], on="scene_id",
                            how="left")
    rows = []
    for rec in merged.to_dict("records"):
        for cat in {rec["category_a"], rec["category_b"]}:
            n_parts = [rec["category_a"], rec["category_b"]].count(cat)
            rows.append({"category": cat, "captures": 1, "frames": rec["frames"],
                         "part_views": rec["frames"] * n_parts * (rec["error"] == ""),
                         "mbytes": rec["bytes"] / 1e6, "failed": int(rec["error"] != "")})
    table = pd.DataFrame(rows).groupby("category", sort=True).sum().reset_index()
    table["mbytes"] = table["mbytes"].round(2)
    return table[columns]
