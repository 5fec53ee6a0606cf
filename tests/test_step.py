"""The XDE reader on real files: names, colours, placements, solid counts of MANIFEST.csv."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cadio.cad.step import read_step, sniff_step
from cadio.errors import StepReadError


def test_solid_counts_match_the_manifest(shared_step_dir: Path, manifest: pd.DataFrame) -> None:
    mismatches = {}
    for relative, row in manifest.iterrows():
        solids = read_step(shared_step_dir / str(relative))
        if len(solids) != int(row["n_solids"]):
            mismatches[relative] = (len(solids), int(row["n_solids"]))
    assert not mismatches


def test_names_colours_and_placements_of_the_as1_assembly(shared_step_dir: Path) -> None:
    solids = read_step(shared_step_dir / "assemblies" / "occt_as1-oc-214-mat.stp")
    names = sorted(s.info.name for s in solids)
    assert names.count("bolt") == 6 and names.count("nut") == 8
    assert {"plate", "rod", "l-bracket"} <= set(names)
    colours = {s.info.name: s.info.colour for s in solids}
    assert colours["bolt"] == "#0000ff" and colours["nut"] == "#ff0000"
    bolts = [s for s in solids if s.info.name == "bolt"]
    origins = {tuple(np.round(s.info.placement[:3, 3], 3)) for s in bolts}
    assert len(origins) == 6  # six instances of one bolt, each placed elsewhere
    assert all("l-bracket-assembly" in s.info.path_in_assembly for s in bolts)
    for s in solids:
        rot = s.info.placement[:3, :3]
        assert np.allclose(rot @ rot.T, np.eye(3), atol=1e-9)


def test_sniff_rejects_non_step_and_truncated(tmp_path: Path, box_step: Path) -> None:
    text = tmp_path / "a.step"
    text.write_text("hello")
    with pytest.raises(StepReadError, match="not a STEP file"):
        sniff_step(text)
    cut = tmp_path / "b.step"
    cut.write_bytes(box_step.read_bytes()[:-200])
    with pytest.raises(StepReadError, match="truncated"):
        sniff_step(cut)
    sniff_step(box_step)


def test_an_assembly_written_twice_in_one_process_has_the_same_bytes(tmp_path: Path) -> None:
    """OCCT numbers assembly occurrences from a process-wide counter; the writer must not."""
    import build123d as bd

    from cadio.cad.step import read_step, write_step

    def assembly() -> bd.Compound:
        a, b = bd.Box(10, 10, 2), bd.Pos(0, 0, 2) * bd.Cylinder(3, 6)
        a.label, b.label = "base", "pin"
        return bd.Compound(children=[a, b], label="pair")

    write_step(assembly(), tmp_path / "first.step")
    write_step(assembly(), tmp_path / "second.step")
    assert (tmp_path / "first.step").read_bytes() == (tmp_path / "second.step").read_bytes()
    assert [s.info.name for s in read_step(tmp_path / "second.step")] == ["base", "pin"]


def test_occurrence_ids_of_any_width_give_the_same_bytes(tmp_path: Path) -> None:
    """A wider id from the process-wide counter moves OCCT's line break (near 80 columns);
    the renumbered occurrence is written the same whatever the counter said."""
    import re

    import build123d as bd

    from cadio.cad.step import _canonical_occurrences, write_step

    a, b = bd.Box(10, 10, 2), bd.Pos(0, 0, 2) * bd.Cylinder(3, 6)
    a.label, b.label = "base-plate-with-a-long-name", "pin"
    write_step(bd.Compound(children=[a, b], label="pair"), tmp_path / "pair.step")
    text = (tmp_path / "pair.step").read_text("latin-1")
    assert len(re.findall(r"NEXT_ASSEMBLY_USAGE_OCCURRENCE\('\d'", text)) == 2
    wide = re.sub(r"(NEXT_ASSEMBLY_USAGE_OCCURRENCE\()'(\d)'(.*?),\$\);",
                  r"\1'12345678\2'\3,$\n  );", text)
    assert wide != text
    assert _canonical_occurrences(wide) == text
