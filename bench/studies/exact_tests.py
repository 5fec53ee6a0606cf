"""How the ``geometric`` tests on exact evidence agree with the labels of a relation dataset.

For each split of a relation dataset (``mateqa train relations`` or
``bench/relation_corpus.py`` builds one in ``<workspace>/datasets/relations``), on its clear
pair views (none of the ten answers near a tolerance boundary), this prints how often the
tests of the ``truth`` input (``tests_for("truth")``) answer parallel, perpendicular,
concentric and coincident as the labels do, with the false and missed mates, beside the tests
before ``coaxial_faces`` and over a grid of the concentric test's two knobs. The knobs are
chosen here, on the training splits, never on held-out files.

Usage:
    .venv/bin/python bench/studies/exact_tests.py --workspace train-workspace

Nothing is asserted. The dataset's ``truth`` evidence must be this code's
(``evidence_digest`` in its ``stamp.json``).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from cadio.evidence.pair_features import PAIR_FEATURES, evidence_digest
from models.geometric import geometric_symmetric, tests_for
from models.relate import RELATIONS

SYMMETRIC = ("parallel", "perpendicular", "concentric", "coincident")


def _line(name: str, answer: np.ndarray, label: np.ndarray) -> str:
    wrong_yes, wrong_no = int((answer & ~label).sum()), int((~answer & label).sum())
    return (f"  {name:34s} agree {100 * float((answer == label).mean()):6.2f}%  "
            f"false {wrong_yes:4d}  missed {wrong_no:4d}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, default=Path("train-workspace"))
    parser.add_argument("--splits", nargs="+", default=["train", "val"])
    args = parser.parse_args()
    folder = args.workspace / "datasets" / "relations"
    stamp = json.loads((folder / "stamp.json").read_text())
    if stamp.get("pair_features") != evidence_digest():
        sys.exit(f"{folder}: its evidence is not this code's; rebuild it")
    exact = tests_for("truth")
    for split in args.splits:
        with np.load(folder / f"{split}.npz") as z:
            features, labels = z["features_truth"], z["labels"].astype(bool)
            clear = ~z["near_boundary"].astype(bool)
        features, labels = features[clear], labels[clear]
        print(f"{split}: {len(labels)} clear pair views of {len(clear)}")
        now = geometric_symmetric(features, exact)
        before = geometric_symmetric(features, replace(exact, coaxial_faces=False))
        for k, name in enumerate(SYMMETRIC):
            label = labels[:, RELATIONS.index(name)]
            print(_line(f"{name}, the exact tests", now[:, k], label))
            if name == "concentric":
                print(_line(f"{name}, before coaxial_faces", before[:, k], label))
        concentric = labels[:, RELATIONS.index("concentric")]
        for spread in (0.1, 0.5, 1.0):
            for gap in (0.0, 0.25, 0.5, 1.0):
                tests = replace(exact, coaxial_spread_mm=spread, face_gap_mm=gap)
                answer = geometric_symmetric(features, tests)[:, 2]
                print(_line(f"concentric, spread {spread}, gap 1 + {gap}", answer, concentric))
    print("columns:", len(PAIR_FEATURES))


if __name__ == "__main__":
    main()
