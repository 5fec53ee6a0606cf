"""Relation methods on CPU: training and inference pairs/s, and the held-out targets.

Usage:
    PYTHONPATH=$PWD .venv/bin/python bench/speed/relations.py [--workspace train-workspace]
        [--run RUN_DIR] [--steps 100] [--pairs 512]

Speed: ``ltn`` training steps on the relation dataset's training split (pairs/s counts each
pair of a batch once), inference of ``ltn`` on held-out pairs (a pair and its swap), and the
``geometric`` baseline (RANSAC fits of both parts + the relation function). Targets (read from
a run's ``relations_summary.csv``, default the newest ``relations-*`` run of the workspace):
``ltn`` on ``completed`` above ``geometric`` and ``mlp`` on ``partial`` for every relation,
``ltn`` on ``truth`` at 99% or more per relation, and ``ltn``'s violation rate below ``mlp``'s.
Nothing is asserted: the bench prints what it measured and whether each target is met.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch


def speed(ws: Path, steps: int, pairs: int) -> pd.DataFrame:
    from models.relate import geometric_decisions
    from models.relation_data import read_split
    from models.relations import RelationConfig
    from models.relations_train import predict_relations, train_relations

    data = ws / "datasets" / "relations"
    train, test = read_split(data / "train.npz"), read_split(data / "test.npz")
    rows = []
    cfg = RelationConfig(steps=steps, eval_every=steps + 1)
    start = time.perf_counter()
    result = train_relations(cfg, train.data("partial"), None)
    seconds = time.perf_counter() - start
    rows.append({"what": "ltn training", "pairs": steps * cfg.batch_size, "seconds": seconds})
    points = test.inputs["partial"][:pairs]
    start = time.perf_counter()
    predict_relations(result.model, points)
    rows.append({"what": "ltn inference (pair and swap)", "pairs": len(points),
                 "seconds": time.perf_counter() - start})
    n = min(pairs, 128)
    mm = 1.0 / test.meta["scale_m_per_mm"].to_numpy(dtype=np.float64)[:n]
    start = time.perf_counter()
    geometric_decisions(test.inputs["partial"][:n], mm)
    rows.append({"what": "geometric (RANSAC + relate)", "pairs": n,
                 "seconds": time.perf_counter() - start})
    table = pd.DataFrame(rows)
    table["pairs_per_s"] = (table["pairs"] / table["seconds"]).round(1)
    return table


def targets(run: Path) -> pd.DataFrame:
    summary = pd.read_csv(run / "relations_summary.csv")
    alls = summary[summary["category"] == "all"].set_index(["input", "method", "relation"])
    acc, viol = alls["accuracy"], alls["violation_rate"]
    rows = []
    for rel in sorted(set(alls.index.get_level_values("relation"))):
        def get(series: pd.Series, i: str, m: str, rel: str = rel) -> float:
            return float(series.get((i, m, rel), np.nan))

        ours = get(acc, "completed", "ltn")
        rows.append({
            "relation": rel, "ltn/completed": ours,
            "geometric/partial": get(acc, "partial", "geometric"),
            "mlp/partial": get(acc, "partial", "mlp"), "ltn/truth": get(acc, "truth", "ltn"),
            "above both": ours > max(get(acc, "partial", "geometric"),
                                     get(acc, "partial", "mlp")),
            "truth >= 99%": get(acc, "truth", "ltn") >= 0.99,
            "violations ltn < mlp": get(viol, "completed", "ltn") < get(viol, "completed",
                                                                        "mlp")})
    return pd.DataFrame(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, default=Path("train-workspace"))
    parser.add_argument("--run", type=Path, default=None)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--pairs", type=int, default=512)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(speed(args.workspace, args.steps, args.pairs).to_string(index=False))
    runs = sorted((args.workspace / "runs").glob("relations-*"))
    run = args.run or (runs[-1] if runs else None)
    if run is None:
        print("no relation run to read targets from (mateqa train relations writes one)")
        return
    table = targets(run)
    print(f"\ntargets from {run}:")
    print(table.round(4).to_string(index=False))
    for col in ("above both", "truth >= 99%", "violations ltn < mlp"):
        print(f"{col}: {int(table[col].sum())}/{len(table)} relations")


if __name__ == "__main__":
    main()
