"""Training the relation networks: corpus scenes, captures, dataset, networks, held-out report.

``mateqa train relations`` runs these steps in the process, after ``mateqa train completion``
in the same training workspace (it reuses that corpus, its split and the completion network):

1. scenes: pairs of the corpus's single parts placed for each relation (``cadio.truth.scenes``),
   every part in the split the completion dataset gave it;
2. captures: each scene rendered from ``views`` cameras around it (``cadio.capture.scan``),
   with the observed points and single-view completion inputs of each part;
3. dataset: every pair in every view, labelled for that view's observer, in three inputs
   (``models.relation_data``);
4. training of ``ltn`` and ``mlp`` on each input (``models.relations``);
5. evaluation of ``ltn``, ``mlp`` and ``geometric`` on the test split (parts no network saw),
   written as a relation report and the model card.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cadio.capture.pairs import INPUTS, PairConfig
from cadio.capture.scan import ScanConfig, capture_batch
from cadio.catalog import read_catalog
from cadio.truth.scenes import SceneConfig, build_scenes, read_scenes
from cadio.workspace import Workspace

Progress = Callable[[str], None]
CORPUS_SCAN = ScanConfig(lengths=(), protocols=("observed",))  # single views: all it needs


def relations_dir(ws: Workspace) -> Path:
    return ws.root / "datasets" / "relations"


def completion_splits(ws: Workspace) -> dict[str, str]:
    """Part id -> split of the completion dataset (``mateqa train completion`` made it).

    Raises:
        FileNotFoundError: the workspace has no completion dataset yet.
    """
    index = pd.read_parquet(ws.root / "datasets" / "completion" / "index.parquet",
                            columns=["part_id", "split"])
    return dict(zip(index["part_id"].astype(str), index["split"].astype(str), strict=True))


def corpus_captures(ws: Workspace, pairs_per_relation: int, seed: int,
                    progress: Progress | None = None) -> list[Path]:
    """The corpus's scenes (reused when the table exists) and their captures (only those
    missing are rendered); the capture files."""
    if not ws.scenes.exists():
        build_scenes(read_catalog(ws.catalog), ws.root,
                     SceneConfig(seed=seed, pairs_per_relation=pairs_per_relation),
                     completion_splits(ws))
    ids = read_scenes(ws.scenes)["scene_id"].astype(str).tolist()
    todo = [s for s in ids if not ws.capture(s).exists()]
    for i in range(0, len(todo), 10):
        for c in capture_batch(todo[i:i + 10], ws, CORPUS_SCAN):
            if progress is not None:
                progress(c.error or c.scene_id)
    return [ws.capture(s) for s in ids if ws.capture(s).exists()]


def build_dataset(ws: Workspace, completion_models: Path,
                  progress: Progress | None = None) -> dict[str, int]:
    """Pair views of every corpus capture into ``datasets/relations/<split>.npz``; reused when
    the captures and the completion network are those it was built from."""
    import json

    from models.evaluate import load_models
    from models.relation_data import build_relation_dataset, read_split

    catalog = read_catalog(ws.catalog)
    categories = dict(zip(catalog["part_id"].astype(str), catalog["category"].astype(str),
                          strict=True))
    models = load_models(completion_models)
    key = ("gan_lstm", "observed")
    captures = sorted(ws.root.glob("captures/*.mcap"))
    stamp = {"captures": [c.stem for c in captures],
             "completion": models.cards[key]["code_version"] if key in models.cards else ""}
    out = relations_dir(ws)
    if (out / "stamp.json").exists() and json.loads((out / "stamp.json").read_text()) == stamp:
        return {p.stem: len(read_split(p).labels) for p in sorted(out.glob("*.npz"))}
    rows = build_relation_dataset(captures, ws, categories, completion_splits(ws),
                                  models.models.get(key), out, PairConfig(), progress)
    (out / "stamp.json").write_text(json.dumps(stamp))
    return rows


@dataclass(frozen=True)
class TrainedRelations:
    """One relation checkpoint: where it went, its method and input, its best step."""

    path: str
    method: str
    input: str
    step: int
    val_accuracy: float
    seconds: float


def train_relation_model(ws: Workspace, method: str, name: str, steps: int, out_dir: Path,
                         on_step: Callable[[], None] | None = None,
                         **overrides: Any) -> TrainedRelations:
    """Train one method on one input's training split; the best checkpoint by validation
    accuracy goes to ``out_dir/<method>-<input>.pt``."""
    from models.relation_data import read_split
    from models.relations import RelationConfig
    from models.relations_train import save_relation_checkpoint, train_relations

    train, val = (read_split(relations_dir(ws) / f"{s}.npz") for s in ("train", "val"))
    cfg = RelationConfig(method=method, steps=steps, **overrides)
    clock = time.perf_counter()
    info = {"input": name, "train_parts": sorted(set(train.meta["part_a"].astype(str))
                                                 | set(train.meta["part_b"].astype(str))),
            "train_pairs": len(train.labels), "val_pairs": len(val.labels),
            "dataset": str(relations_dir(ws).relative_to(ws.root))}
    result = train_relations(cfg, train.data(name), val.data(name), data_info=info,
                             progress=None if on_step is None else lambda e: on_step())
    ckpt = result.checkpoint
    path = save_relation_checkpoint(out_dir / f"{method}-{name}.pt", ckpt, half=True)
    return TrainedRelations(str(path), method, name, int(ckpt["step"]),
                            float(ckpt["metrics"].get("val_accuracy", np.nan)),
                            time.perf_counter() - clock)


def evaluate_relations(ws: Workspace, models_dir: Path, run_dir: Path,
                       progress: Progress | None = None) -> Path:
    """Every method on every input of the test split; the run's relation report."""
    from models.relate import METHODS, decide, load_relation_models
    from models.relation_data import read_split
    from reports.relations import pairs_frame, write_relation_report

    test = read_split(relations_dir(ws) / "test.npz")
    models = load_relation_models(models_dir)
    meta = test.meta
    mm = 1.0 / meta["scale_m_per_mm"].to_numpy(dtype=np.float64)
    keys = [((s, a, v), (s, b, v)) for s, a, b, v in
            zip(meta["scene"], meta["part_a"], meta["part_b"], meta["view"], strict=True)]
    rows = []
    for name in INPUTS:
        for method in METHODS:
            out = decide(test.inputs[name], mm, method, models.models.get((method, name)),
                         keys)
            if out is None:
                continue
            rows += _rows(meta, test.labels, name, method, *out)
            if progress is not None:
                progress(f"{method}/{name}")
    return write_relation_report(run_dir, pairs_frame(rows), notes=[
        f"Held-out test split of the training corpus: {len(meta)} pair views of "
        f"{meta['scene'].nunique()} scenes; checkpoints {models.versions()}."])


def _rows(meta: pd.DataFrame, labels: np.ndarray, name: str, method: str, decided: np.ndarray,
          confidence: np.ndarray, broken: np.ndarray) -> list[dict[str, Any]]:
    from models.relate import RELATIONS

    records = meta.to_dict("records")
    return [{"scene": m["scene"], "view": int(m["view"]), "part_a": m["part_a"],
             "part_b": m["part_b"], "category": m["category"], "input": name, "method": method,
             "relation": rel, "truth": bool(labels[i, k]), "predicted": bool(decided[i, k]),
             "confidence": float(confidence[i, k]), "near_boundary": bool(m["near_boundary"]),
             "violation": bool(broken[i, k])}
            for i, m in enumerate(records) for k, rel in enumerate(RELATIONS)]


def dataset_rows(ws: Workspace) -> pd.DataFrame:
    """Pair views, scenes and parts per split of the relation dataset."""
    from models.relation_data import read_split

    rows = []
    for split in ("train", "val", "test"):
        path = relations_dir(ws) / f"{split}.npz"
        if path.exists():
            meta = read_split(path).meta
            rows.append({"split": split, "pair_views": len(meta),
                         "scenes": meta["scene"].nunique(),
                         "parts": len(set(meta["part_a"]) | set(meta["part_b"])),
                         "near_boundary": int(meta["near_boundary"].sum())})
    return pd.DataFrame(rows)


def write_relation_card(ws: Workspace, out_dir: Path, run_dir: Path, command: str,
                        config: dict[str, Any]) -> Path:
    """``MODEL_CARD.md`` beside the relation checkpoints, from the held-out report."""
    from models.relations_train import load_relation_model
    from reports.tables import markdown_table

    ckpts = []
    for path in sorted(out_dir.glob("*.pt")):
        _, _, ckpt = load_relation_model(path)
        ckpts.append({"file": path.name, "method": ckpt["method"],
                      "input": ckpt["data"].get("input", ""), "step": ckpt["step"],
                      "MB": round(path.stat().st_size / 1e6, 2),
                      "val_accuracy": round(float(ckpt["metrics"].get("val_accuracy",
                                                                      np.nan)), 4),
                      "val_ece": round(float(ckpt["metrics"].get("val_ece_calibrated",
                                                                 np.nan)), 4),
                      "code": ckpt["code_version"]})
    text = "\n".join([
        "# Relation checkpoints", "",
        "The neural-logic relation network `ltn` (a five-layer grounding MLP over 600 points "
        "per part, one Logic Tensor Network predicate per relation, trained on the labelled "
        "facts and the fuzzy-logic axioms) and `mlp` (the same network on the facts only), one "
        "checkpoint per input (`truth`: CAD surface samples, `partial`: the segmented scan, "
        "`completed`: the completion network's shape). The networks see the points in the "
        "observer's frame only. Load with `torch.load(weights_only=True)`.", "",
        "## Checkpoints", "", markdown_table(pd.DataFrame(ckpts)), "",
        "## Data", "", "Pair scenes of the completion corpus's single parts, every part in the "
        "split the completion dataset gave it (the nightly's sample parts are never trained "
        "on); each view relabels the directional relations for its own camera.", "",
        markdown_table(dataset_rows(ws)), "",
        "## Training", "", ", ".join(f"{k} {v}" for k, v in config.items()), "",
        f"Held-out report: `{run_dir.name}` of the training workspace.", "",
        (run_dir / "relations.md").read_text(), "", "Trained with:", "", f"    {command}", ""])
    path = out_dir / "MODEL_CARD.md"
    path.write_text(text)
    return path
