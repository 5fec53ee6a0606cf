"""How much the pair evidence says about the CAD's mates at a given number of points per part.

The relation networks read 600 points per part (the paper's grounding MLP), and the pair
evidence (``cadio.evidence.pair_features``: contact plane and axis, part axes, dominant plane
directions) used to be measured on the same 600. The mates it stands for are decided at 0.1-1 mm
on faces that may be a few percent of a part's surface. This measures the evidence on exact CAD
samples of the relation dataset's clear assembly pairs (one row per pair, not per view: CAD
samples do not change with the view) at each density asked for, and how well it separates each
symmetric relation: a gradient-boosted classifier per relation fitted on the train split's
pairs, scored on the test split's pairs of real assemblies (files of ``--shared``) and of the
sample families apart: ROC AUC, F1 at 0.5 and the best F1 over thresholds (which peeks at the
test labels: an upper bound of the evidence, not a method).

Usage:
    .venv/bin/python bench/studies/evidence_density.py --workspace train-workspace \
        [--points 600 3000]

Nothing is asserted: it prints the figures and the seconds each density's evidence took.
"""

from __future__ import annotations

import argparse
import json
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np
import pandas as pd

from cadio.evidence.cad_samples import placed_cad_samples
from cadio.evidence.pair_features import pair_features, part_cloud
from cadio.workspace import features_of_mesh, read_mesh
from models.relation_data import read_split

SYMMETRIC = {6: "parallel", 7: "perpendicular", 8: "concentric", 9: "coincident"}


def _shot_features(job: tuple[str, list[dict], list[tuple[str, str]], int]) -> list[np.ndarray]:
    """The evidence of one shot's pairs: each part's n CAD samples placed as in the shot (mm),
    with the exact normals of their faces as the ``truth`` evidence takes them."""
    _, parts, pairs, n = job
    by_id = {p["part_id"]: p for p in parts}
    clouds = {}
    for pid in {x for pair in pairs for x in pair}:
        p = by_id[pid]
        pose = np.asarray(p["pose_mm"], dtype=np.float64).reshape(4, 4)
        mesh = Path(p["mesh_path"])
        samples = placed_cad_samples(read_mesh(mesh), features_of_mesh(mesh), pid, pose, n, 1.0)
        clouds[pid] = part_cloud(samples[:, :3], normals=samples[:, 3:])
    return [pair_features(clouds[a], clouds[b]) for a, b in pairs]


def evidence(workspace: Path, split: str, n: int, shots: pd.DataFrame
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(features (P, F), labels (P, 10), from a real assembly (P,)) of a split's clear
    assembly pairs at n CAD samples per part."""
    data = read_split(workspace / "datasets" / "relations" / f"{split}.npz")
    meta = data.meta
    keep = (meta["kind"] == "assembly").to_numpy() & ~meta["near_boundary"].to_numpy()
    pairs = meta[keep].drop_duplicates(["scene", "part_a", "part_b"])
    jobs = [(str(scene), json.loads(shots.at[scene, "parts"]),
             list(zip(g["part_a"], g["part_b"], strict=True)), n)
            for scene, g in pairs.groupby("scene")]
    with Pool(2) as pool:
        found = pool.map(_shot_features, jobs)
    by_pair = {(job[0], *pair): f for job, fs in zip(jobs, found, strict=True)
               for pair, f in zip(job[2], fs, strict=True)}
    x = np.stack([by_pair[(r.scene, r.part_a, r.part_b)] for r in pairs.itertuples()])
    root = str(workspace.resolve())
    real = ~pairs["scene"].map(lambda s: str(shots.at[s, "group"]).startswith(root)).to_numpy()
    return x, data.labels[pairs.index.to_numpy()], real


def main() -> None:
    from sklearn.ensemble import HistGradientBoostingClassifier
    from sklearn.metrics import precision_recall_curve, roc_auc_score

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workspace", type=Path, required=True)
    ap.add_argument("--points", type=int, nargs="+", default=[600, 3000])
    args = ap.parse_args()
    shots = pd.read_parquet(args.workspace / "datasets" / "corpus" / "shots.parquet"
                            ).set_index("shot")
    for n in args.points:
        clock = time.perf_counter()
        x_train, y_train, _ = evidence(args.workspace, "train", n, shots)
        x_test, y_test, real = evidence(args.workspace, "test", n, shots)
        print(f"{n} points per part: {len(x_train)} train pairs, {len(x_test)} test pairs "
              f"({real.sum()} of real assemblies); evidence {time.perf_counter() - clock:.0f} s")
        for col, name in SYMMETRIC.items():
            fit = HistGradientBoostingClassifier(random_state=0).fit(x_train, y_train[:, col])
            for tag, rows in (("real", real), ("families", ~real)):
                truth = y_test[rows, col]
                if truth.all() or not truth.any():
                    continue
                score = fit.predict_proba(x_test[rows])[:, 1]
                precision, recall, _ = precision_recall_curve(truth, score)
                best = np.max(2 * precision * recall / np.maximum(precision + recall, 1e-12))
                said = score > 0.5
                f1 = 2 * np.sum(said & truth) / max(said.sum() + truth.sum(), 1)
                print(f"  {name:13s} {tag:8s} positives {truth.sum():3d}/{len(truth):3d}  "
                      f"AUC {roc_auc_score(truth, score):.3f}  F1 {f1:.3f}  best F1 {best:.3f}")


if __name__ == "__main__":
    main()
