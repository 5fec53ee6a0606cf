"""A night on the real files no network trained on: the library CSV of the held-out files.

``mateqa train`` holds out half of the shared real STEP files whole (their split is "test" in
the corpus's ``groups.csv``: every solid of a held-out assembly, and, through the shape keys,
every other file's copy of a held-out geometry). This writes those files as a library CSV
(path relative to the CSV, category) and prints the nightly command that judges the shipped
checkpoints where users meet them:

    .venv/bin/python -m models.training.heldout --corpus train-workspace/datasets/corpus \\
        --shared ../shared/data/step --out heldout/library.csv
    .venv/bin/mateqa nightly --library heldout/library.csv --workspace heldout/ws

Without a training workspace (a fresh machine), ``--corpus`` may name a folder without
``groups.csv``: the files are then drawn by the corpus's own rule (``corpus_splits``: a draw
from sha256(seed, the file's path), half of the real files held out), with each file keyed by
its absolute path, as ``mateqa train --shared`` with an absolute folder keys them. A training
run given a relative ``--shared`` keyed them otherwise; then only its ``groups.csv`` says.

The night itself also leaves out of its scores any part a checkpoint trained on (the
checkpoints list their training parts), so a file listed here by mistake cannot flatter them.
"""

from __future__ import annotations

import argparse
import csv
import logging
import os
import sys
from pathlib import Path

from cadio.cad.ingest import discover
from models.training.corpus import corpus_splits
from models.training.prepare import corpus_fractions

log = logging.getLogger(__name__)


def heldout_files(groups_csv: Path, shared: Path) -> list[tuple[Path, str]]:
    """(file, category) of every held-out ("test") source file under ``shared``."""
    shared = shared.resolve()
    out = []
    with groups_csv.open() as fh:
        for row in csv.DictReader(fh):
            path = Path(row["source"]).resolve()
            if row["split"] == "test" and shared in path.parents:
                out.append((path, path.relative_to(shared).parts[0]))
    return sorted(out)


def drawn_heldout_files(shared: Path, seed: int = 0) -> list[tuple[Path, str]]:
    """(file, category) of every file under ``shared`` that the corpus's split rule holds out,
    each keyed by its absolute path (no training workspace needed)."""

    shared = shared.resolve()
    found = {str(f.path): f for f in discover(shared)}
    groups = {path: [path] for path in found}
    split, _ = corpus_splits(groups, {}, seed, corpus_fractions(shared / ".none", shared))
    return sorted((Path(p), found[p].category) for p, s in split.items() if s == "test")


def write_library(files: list[tuple[Path, str]], out: Path) -> dict[str, int]:
    """The files as a library CSV (path relative to the CSV, category); files per category."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["path", "category"])
        for path, category in files:
            writer.writerow([os.path.relpath(path, out.parent.resolve()), category])
    by_category: dict[str, int] = {}
    for _, category in files:
        by_category[category] = by_category.get(category, 0) + 1
    return by_category


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m models.training.heldout",
                                     description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--corpus", type=Path, default=Path("train-workspace/datasets/corpus"))
    parser.add_argument("--shared", type=Path, default=Path("../shared/data/step"))
    parser.add_argument("--out", type=Path, default=Path("heldout/library.csv"))
    parser.add_argument("--seed", type=int, default=0, help="the training run's seed")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
    groups = args.corpus / "groups.csv"
    if groups.exists():
        files = heldout_files(groups, args.shared)
    else:
        log.info("%s: absent; the held-out files are drawn by the corpus's split rule", groups)
        files = drawn_heldout_files(args.shared, args.seed)
    by_category = write_library(files, args.out)
    log.info("%d held-out files %s -> %s", len(files), by_category, args.out)
    log.info("mateqa nightly --library %s --workspace %s", args.out, args.out.parent / "ws")
    return 0


if __name__ == "__main__":
    sys.exit(main())
