"""A night on the real files no network trained on: the library CSV of the held-out files.

``mateqa train`` holds out half of the shared real STEP files whole (their split is "test" in
the corpus's ``groups.csv``: every solid of a held-out assembly, and, through the shape keys,
every other file's copy of a held-out geometry). This writes those files as a library CSV
(path relative to the CSV, category) and prints the nightly command that judges the shipped
checkpoints where users meet them:

    .venv/bin/python bench/heldout_night.py --corpus train-workspace/datasets/corpus \\
        --shared ../shared/data/step --out heldout/library.csv
    .venv/bin/mateqa nightly --library heldout/library.csv --workspace heldout/ws

The night itself also leaves out of its scores any part a checkpoint trained on (the
checkpoints list their training parts), so a file listed here by mistake cannot flatter them.
"""

from __future__ import annotations

import argparse
import csv
import os
from pathlib import Path


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--corpus", type=Path, default=Path("train-workspace/datasets/corpus"))
    parser.add_argument("--shared", type=Path, default=Path("../shared/data/step"))
    parser.add_argument("--out", type=Path, default=Path("heldout/library.csv"))
    args = parser.parse_args()
    files = heldout_files(args.corpus / "groups.csv", args.shared)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["path", "category"])
        for path, category in files:
            writer.writerow([os.path.relpath(path, args.out.parent.resolve()), category])
    by_category: dict[str, int] = {}
    for _, category in files:
        by_category[category] = by_category.get(category, 0) + 1
    print(f"{len(files)} held-out files {by_category} -> {args.out}")
    print(f"mateqa nightly --library {args.out} --workspace {args.out.parent / 'ws'}")


if __name__ == "__main__":
    main()
