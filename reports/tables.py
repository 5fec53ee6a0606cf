"""Per-category tables of each stage, and Markdown tables. Pure pandas, no CAD, no torch.

Inputs are the catalog and the typed summaries the stages return (``cadio.contracts``);
outputs are DataFrames that ``reports.render`` puts into the run's report files.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import pandas as pd

from cadio.contracts import CaptureSummary, MatesSummary


def printable(value: object) -> str:
    """``str(value)`` on one line: every character that is not printable (newline, tab, a
    terminal's escape sequences, bidirectional overrides) as its Python escape (``\\n``,
    ``\\x1b``). Names come from input files and folders; this is how they reach a console."""
    text = str(value)
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else ascii(c)[1:-1] for c in text)


def markdown_text(value: object) -> str:
    """``value`` as inline Markdown text that stays in its table cell or list item: on one
    line (``printable``), ``|`` escaped, and ``<``, ``>`` as entities (no raw HTML)."""
    text = printable(value).replace("|", "\\|")
    return text.replace("<", "&lt;").replace(">", "&gt;")


def markdown_table(frame: pd.DataFrame) -> str:
    """A GitHub-flavoured Markdown table (no optional dependency on tabulate); every cell
    through ``markdown_text``."""
    cols = [markdown_text(c) for c in frame.columns]
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for row in frame.itertuples(index=False):
        out.append("| " + " | ".join(markdown_text(v) for v in row) + " |")
    return "\n".join(out)


def files_table(catalog: pd.DataFrame) -> pd.DataFrame:
    """One row per source file: ok if any of its solids is ok, parts ok, parts reused."""
    if catalog.empty:
        return pd.DataFrame(columns=["category", "source", "file_status", "parts", "cached"])
    return (
        catalog.groupby(["category", "source"], sort=True)
        .agg(file_status=("status", lambda s: "ok" if (s == "ok").any() else str(s.iloc[0])),
             parts=("status", lambda s: int((s == "ok").sum())),
             cached=("cached", lambda s: int(s.sum())))
        .reset_index()
    )


def ingest_table(files: pd.DataFrame) -> pd.DataFrame:
    """Per category: files found, ok, failed, skipped, parts, parts reused from the cache."""
    return (
        files.groupby("category", sort=True)
        .agg(files=("source", "count"),
             ok=("file_status", lambda s: int((s == "ok").sum())),
             failed=("file_status", lambda s: int((s == "failed").sum())),
             skipped=("file_status", lambda s: int((s == "skipped").sum())),
             parts=("parts", "sum"),
             cached=("cached", "sum"))
        .reset_index()
    )


def mates_table(assemblies: Sequence[MatesSummary]) -> pd.DataFrame:
    """Per category: assemblies, failures, parts, pairs, pairs in contact, face mates, part
    relations and joints (counts of the assemblies that went through)."""
    columns = ["category", "assemblies", "failed", "parts", "pairs", "contact_pairs",
               "face_mates", "relations", "joints"]
    if not assemblies:
        return pd.DataFrame(columns=columns)
    frame = pd.DataFrame([{
        "category": a.category, "assemblies": 1, "failed": int(not a.ok), "parts": a.n_parts,
        "pairs": a.n_pairs, "contact_pairs": a.n_contact_pairs, "face_mates": a.face_mates,
        "relations": a.relations, "joints": a.joints} for a in assemblies])
    return frame.groupby("category", sort=True).sum().reset_index()[columns]


def joints_table(assemblies: Sequence[MatesSummary]) -> pd.DataFrame:
    """Joint types found, per category (suggested CAD joint names)."""
    rows = [{"category": a.category, "joint": j, "count": n}
            for a in assemblies if a.ok for j, n in a.joint_types.items()]
    if not rows:
        return pd.DataFrame(columns=["category", "joint", "count"])
    return (pd.DataFrame(rows).groupby(["category", "joint"], sort=True)["count"].sum()
            .reset_index())


def scenes_table(scenes: pd.DataFrame) -> pd.DataFrame:
    """Scenes per split and intended relation (or ``contact``: touching, meant as no mate),
    with the share where the intent holds."""
    if scenes.empty:
        return pd.DataFrame(columns=["split", "intended", "scenes", "holds"])
    # a touching pair meant as no relation "holds" when it is no face mate
    holds = [bool(row[row["intended"]]) if row["intended"] in row
             else not (row["coincident"] or row["concentric"])
             for row in scenes.to_dict("records")]
    table = (scenes.assign(holds=holds).groupby(["split", "intended"], sort=True)
             .agg(scenes=("scene_id", "count"), holds=("holds", "mean")).reset_index())
    table["holds"] = table["holds"].round(3)
    return table


def captures_table(captures: Sequence[CaptureSummary], scenes: pd.DataFrame,
                   part_categories: Mapping[str, str] | None = None) -> pd.DataFrame:
    """Per category: captures, frames and part views captured (a pair counts in both parts'
    categories), bytes on disk, failures. A capture of no scene (an assembly as placed, a part
    alone, a recording) counts in the categories of the parts it scored (``part_categories``:
    part id -> category); one with none known counts as "unknown"."""
    columns = ["category", "captures", "frames", "part_views", "mbytes", "failed"]
    if not captures:
        return pd.DataFrame(columns=columns)
    cats = {str(r["scene_id"]): (str(r["category_a"]), str(r["category_b"]))
            for r in scenes.to_dict("records")}
    known = part_categories or {}
    rows = []
    for c in captures:
        parts = cats.get(c.scene_id) or tuple(known[p] for p in c.scored if p in known)
        parts = parts or ("unknown",)
        for cat in sorted(set(parts)):
            rows.append({"category": cat, "captures": 1, "frames": c.frames,
                         "part_views": c.frames * parts.count(cat) * (c.error == ""),
                         "mbytes": c.bytes / 1e6, "failed": int(c.error != "")})
    table = pd.DataFrame(rows).groupby("category", sort=True).sum().reset_index()
    table["mbytes"] = table["mbytes"].round(2)
    return table[columns]
