"""The relation networks' training data on a bare machine, in under an hour on two cores.

``mateqa train relations`` reads the corpus that ``mateqa train completion`` builds: every shot
(parts alone, pairs, assemblies), single views and sequences, both protocols, 104 min on two
cores. The relation networks need only the pair and assembly shots, and of those only the
single observed views (what the completion network completes). This builds that much of the
corpus in a training workspace, with the same library, splits, scenes and shot ids, then labels
it and builds the relation dataset with the shipped completion network. After that,
``mateqa train relations --workspace W`` trains at once (a network takes 3-5 min).

    .venv/bin/python bench/relation_corpus.py --workspace train-workspace \\
        --shared ../shared/data/step

Measured on two cores (2026-11-26): library, variants and ingest 2.4 min, scenes about one
minute, 1,719 shots rendered in 17 min (1.7 shots/s), labels and the relation dataset 16 min
(10,714 / 1,809 / 3,095 pair views). With the four contact families (2026-11-27, 280
assemblies in all) the 80 new assemblies were rendered and labelled in 70 s beside the reused
shots and the dataset was rebuilt in 26 min: 11,757 / 1,913 / 3,363 pair views, as the shipped
relation card records. ``--contact-pairs`` adds touching pairs to the scenes, as
``mateqa train completion --contact-pairs`` does (about 3 s a pair on one core, and its shots
beside).

The corpus is stamped with its own configuration, so ``mateqa train completion`` refuses it;
give completion a workspace of its own. ``--shared`` is resolved to an absolute folder: the
corpus's split draw keys each file by its path as given, and the shipped checkpoints' corpus
was given an absolute one (``python -m models.training.heldout`` relies on that).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cadio.cad.ingest import IngestConfig
from cadio.capture.examples import OBSERVED, ExampleConfig
from cadio.sandbox import Limits
from cadio.tolerances import DEFAULT_TOLERANCES
from cadio.workspace import Workspace
from models.evaluate import SHIPPED
from models.training.corpus import KINDS, CorpusConfig
from models.training.prepare import prepare_corpus
from models.training.relations import build_dataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, default=Path("train-workspace"))
    parser.add_argument("--shared", type=Path, default=None)
    parser.add_argument("--variants", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--pairs-per-relation", type=int, default=150)
    parser.add_argument("--contact-pairs", type=int, default=0)
    parser.add_argument("--clearance-pairs", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    clock = time.perf_counter()
    ws = Workspace(args.workspace.resolve())
    limits = Limits(workers=args.workers, seconds=600)
    example = ExampleConfig(n_in=32, n_out=64, grid_margin=DEFAULT_TOLERANCES.grid_margin)
    cfg = CorpusConfig(example=example, lengths=(), protocols=(OBSERVED,), seed=args.seed)
    corpus = prepare_corpus(ws, args.shared.resolve() if args.shared else None, args.variants,
                            args.seed, IngestConfig(limits=limits), cfg,
                            pairs_per_relation=args.pairs_per_relation,
                            contact_pairs=args.contact_pairs,
                            clearance_pairs=args.clearance_pairs,
                            kinds=tuple(k for k in KINDS if k != "alone"))
    print(f"corpus: {corpus.parts} parts {corpus.splits}, shots {corpus.shots}, "
          f"{corpus.failed} failed ({time.perf_counter() - clock:.0f} s)", flush=True)
    rows = build_dataset(ws, SHIPPED, limits)
    print(f"relation dataset: pair views per split {rows} ({time.perf_counter() - clock:.0f} s)")
    print(f"next: mateqa train relations --workspace {args.workspace}")


if __name__ == "__main__":
    main()
