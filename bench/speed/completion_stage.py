"""Benchmark of the night's completion stage: where a part's scoring time goes.

On a workspace a night captured: the input folders the stage scores (``part_inputs``, a
seeded draw of ``--folders`` of them), each folder's examples read, completed by every method
and scored as ``models.evaluate.score_files`` does it, with the wall seconds of each phase:
reading the examples, the learned networks (a folder's examples ``PREDICT_BATCH`` to a forward
pass), each method without learning (``registered``: the library's CAD found in the view by
the search route, then voxelized), the scores against the truth, and the shipped method's ICP
residual. One process, one thread of the libraries' (as a stage's worker runs). The stage's
own seconds are in the night's log (``completion``); this says which phase to work on.

Usage: ``.venv/bin/python bench/speed/completion_stage.py WORKSPACE [--folders 16] [--seed 0]``
"""

from __future__ import annotations

import argparse
import random
import sys
import time
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run from anywhere

import pandas as pd
import torch

from cadio.capture.examples import read_example
from cadio.inspect.completion import LibraryCad
from cadio.workspace import Workspace
from models.completions import COMPLETIONS, ours
from models.evaluate import (
    SHIPPED,
    learned_solids,
    load_models,
    part_inputs,
    register_completion,
    score_example,
)


def measure(ws: Workspace, folders: list[Path], models_dir: Path) -> pd.DataFrame:
    """Seconds per phase (and per method without learning) over the folders' examples."""
    models = load_models(models_dir)
    cad = LibraryCad(ws)
    seconds: dict[str, float] = defaultdict(float)
    examples = scores = failed = 0
    for folder in folders:
        clock = time.perf_counter()
        read = [read_example(p) for p in sorted(folder.glob("*-*.npz"))]
        seconds["read"] += time.perf_counter() - clock
        clock = time.perf_counter()
        learned = learned_solids(models, read)
        seconds["learned networks"] += time.perf_counter() - clock
        for example, solids in zip(read, learned, strict=True):
            preds = dict(solids)
            for method in COMPLETIONS.entries():
                clock = time.perf_counter()
                if method.solid is not None:
                    preds[method.name] = method.solid(example)
                elif method.from_cad is not None:
                    scene = cad.of(str(example.meta.get("capture", "")))
                    if scene is not None:
                        preds[method.name] = method.from_cad(example, scene)
                else:
                    continue
                seconds[method.name] += time.perf_counter() - clock
            if example.target is None:
                continue
            clock = time.perf_counter()
            try:
                scores += len(score_example(example, preds, "test", "bench"))
            except ValueError:  # an empty truth grid: the stage's failure row, not timed on
                failed += 1
                continue
            finally:
                seconds["scores"] += time.perf_counter() - clock
            clock = time.perf_counter()
            if ours().name in preds:
                register_completion(example, preds[ours().name], example.target.shape[0])
            seconds["icp residual"] += time.perf_counter() - clock
            examples += 1
    total = sum(seconds.values())
    rows = [{"phase": name, "seconds": s, "share": s / total, "ms per example":
             1000 * s / max(examples, 1)} for name, s in seconds.items()]
    rows.append({"phase": "all", "seconds": total, "share": 1.0,
                 "ms per example": 1000 * total / max(examples, 1)})
    print(f"{len(folders)} folders, {examples} examples scored ({failed} failed), "
          f"{scores} scores")
    return pd.DataFrame(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path, help="a workspace a night captured")
    parser.add_argument("--folders", type=int, default=16, help="input folders drawn")
    parser.add_argument("--seed", type=int, default=0, help="seed of the draw")
    parser.add_argument("--models", type=Path, default=SHIPPED, help="completion checkpoints")
    args = parser.parse_args()
    torch.set_num_threads(1)
    ws = Workspace(args.workspace)
    folders = part_inputs(sorted((ws.root / "inputs").iterdir()))
    random.Random(args.seed).shuffle(folders)
    table = measure(ws, folders[:args.folders], args.models)
    print(table.round(3).to_string(index=False))


if __name__ == "__main__":
    main()
