"""The held-out library: every file a training run held out whole, as a library a night reads."""

from __future__ import annotations

import csv
from pathlib import Path

from models.training.heldout import heldout_files, write_library


def test_the_held_out_files_of_a_corpus_become_a_library_csv(tmp_path: Path) -> None:
    shared = tmp_path / "shared"
    for rel in ("fasteners/bolt.step", "fasteners/nut.step", "assemblies/gearbox.stp"):
        (shared / rel).parent.mkdir(parents=True, exist_ok=True)
        (shared / rel).write_text("ISO-10303-21;")
    groups = tmp_path / "groups.csv"
    groups.write_text("source,split\n"
                      f"{shared / 'fasteners/bolt.step'},test\n"
                      f"{shared / 'fasteners/nut.step'},train\n"
                      f"{shared / 'assemblies/gearbox.stp'},test\n"
                      f"{tmp_path / 'elsewhere.step'},test\n")
    files = heldout_files(groups, shared)
    assert [(p.name, c) for p, c in files] == [("gearbox.stp", "assemblies"),
                                               ("bolt.step", "fasteners")]
    out = tmp_path / "heldout" / "library.csv"
    assert write_library(files, out) == {"assemblies": 1, "fasteners": 1}
    with out.open() as fh:
        rows = list(csv.DictReader(fh))
    assert [(out.parent / r["path"]).resolve() for r in rows] == [p for p, _ in files]
