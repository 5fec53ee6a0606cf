"""The CAD's own answers as an assembly's predictions, for the export tests: every predicted
concentric or coincident mate has a CAD face mate behind it, so each becomes a constraint."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

if TYPE_CHECKING:
    from cadio.cad.step import StepSolid
    from cadio.export.predictions import AssemblyMates


def oracle_predictions(mates: pd.DataFrame, wrong_concentric: bool = False) -> pd.DataFrame:
    """One confident view per pair of the mates table: its part-level relations, and
    concentric or coincident wherever it has such a face mate. ``wrong_concentric`` adds a
    concentric answer to the first pair the CAD has none for (a mate that is no constraint)."""
    from cadio.export.predictions import RELATIONS

    rows = []
    for (a, b), g in mates.groupby(["part_a", "part_b"], sort=False):
        held = set(g[g["level"].isin(["part", "face"])]["relation"])
        if wrong_concentric and "concentric" not in held:
            held, wrong_concentric = held | {"concentric"}, False
        rows += [{"scene": "assembly-x", "view": 0, "part_a": a, "part_b": b, "relation": rel,
                  "truth": rel in held, "predicted": rel in held, "confidence": 0.99}
                 for rel in RELATIONS]
    return pd.DataFrame(rows)


def oracle_record(step: Path, wrong_concentric: bool = False
                  ) -> tuple[AssemblyMates, list[StepSolid], pd.DataFrame]:
    """The export record of ``step`` with the CAD's answers as predictions, the file's
    solids and its CAD mates table."""
    from cadio.cad.step import read_step
    from cadio.export.predictions import assembly_mates
    from cadio.truth.mates import read_assembly_mates

    solids = read_step(step)
    catalog = pd.DataFrame({
        "part_id": [f"p-{s.info.index}" for s in solids],
        "solid_index": [s.info.index for s in solids],
        "name": [s.info.name for s in solids],
        "path_in_assembly": [s.info.path_in_assembly for s in solids],
        "placement": [json.dumps(s.info.placement.ravel().tolist()) for s in solids]})
    mates = read_assembly_mates(step, part_ids=dict(
        zip(catalog["solid_index"], catalog["part_id"], strict=True))).table
    record = assembly_mates(step.stem, "assemblies", str(step), "", catalog, mates,
                            oracle_predictions(mates, wrong_concentric))
    return record, solids, mates
