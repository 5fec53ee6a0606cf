"""Training the relation networks: the corpus's labelled pairs, networks, held-out report.

``mateqa train relations`` runs these steps in the process, after ``mateqa train completion``
in the same training workspace (it reuses that corpus, its split and the completion network):

1. labels: the pairs of every pair scene and assembly of the corpus, labelled view by view by
   the truth of placed parts (``cadio.truth.corpus_labels``), one crash-isolated job per shot
   (kept under the corpus's ``labels/``: a rerun labels only new shots);
2. dataset: every labelled pair in every view in three inputs, with the pair evidence of each
   (``models.relation_data``); the completion network completes each part from that view;
3. training of ``ltn`` and ``mlp`` on each input (``models.relations``);
4. evaluation of ``ltn``, ``mlp`` and ``geometric`` on the test split (parts no network saw),
   written as a relation report and the model card.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cadio.catalog import read_catalog
from cadio.evidence.pair_features import evidence_digest
from cadio.evidence.pairs import DEFAULT_PAIRS
from cadio.sandbox import Limits
from cadio.truth.corpus_labels import LabelJob, LabelPart, ShotLabels, label_shots
from cadio.workspace import Workspace, atomic_write
from models.completions import ours as completion_ours
from models.geometric import evidence_gains, evidence_names, tests_for
from models.relation_inputs import INPUTS, trained
from models.relation_methods import RELATION_METHODS
from models.training.corpus import Shot, read_index, read_shots
from models.training.prepare import dataset_dir

Progress = Callable[[str], None]


def relations_dir(ws: Workspace) -> Path:
    return ws.root / "datasets" / "relations"


def label_jobs(ws: Workspace, shots: list[Shot]) -> list[LabelJob]:
    """A labelling job for every pair scene and assembly of the corpus (their parts' STEP
    files from the catalog, each view's forward axis from the shot's views)."""
    catalog = read_catalog(ws.catalog)
    where = {str(r.part_id): (str(r.source), int(r.solid_index)) for r in catalog.itertuples()}
    jobs = []
    for shot in shots:
        path = dataset_dir(ws) / "views" / f"{shot.shot_id}.npz"
        if shot.kind == "alone" or not path.exists():
            continue
        with np.load(path) as z:
            views, first = np.unique(z["view"], return_index=True)
            forward = [tuple(float(x) for x in z["world_to_camera"][k][2, :3]) for k in first]
        parts = tuple(LabelPart(p.instance, p.part_id, *where[p.part_id],
                                str(ws.features(p.part_id)), p.pose_mm) for p in shot.parts)
        jobs.append(LabelJob(shot.shot_id, shot.kind, parts, tuple(int(v) for v in views),
                             tuple(forward)))  # type: ignore[arg-type]
    return jobs


def label_corpus(ws: Workspace, limits: Limits, progress: Progress | None = None
                 ) -> dict[str, ShotLabels]:
    """The labels of every labelled shot of the corpus, labelling the shots not yet labelled."""
    folder = dataset_dir(ws) / "labels"
    folder.mkdir(parents=True, exist_ok=True)
    jobs = label_jobs(ws, read_shots(dataset_dir(ws) / "shots.parquet"))
    todo = [j for j in jobs if not _labelled(folder / f"{j.shot}.npz")]
    for job, labels, reason in label_shots(todo, limits):
        if labels is not None:
            with atomic_write(folder / f"{job.shot}.npz") as fh:
                np.savez(fh, pairs=labels.pairs, views=labels.views, truth=labels.truth,
                         near=labels.near, joints=labels.joints)
        if progress is not None:
            progress(reason or job.shot)
    out = {}
    for job in jobs:
        path = folder / f"{job.shot}.npz"
        if path.exists():
            with np.load(path) as z:
                out[job.shot] = ShotLabels(job.shot, z["pairs"], z["views"], z["truth"],
                                           z["near"], z["joints"])
    return out


def _labelled(path: Path) -> bool:
    """Whether a shot's labels are stored, with every array this code reads (labels written
    before the joints were labelled are labelled anew)."""
    if not path.exists():
        return False
    with np.load(path) as z:
        return "joints" in z.files


def build_dataset(ws: Workspace, completion_models: Path, limits: Limits,
                  progress: Progress | None = None) -> dict[str, int]:
    """Pair views of every labelled corpus shot into ``datasets/relations/<split>.npz``;
    reused when the labels and the completion network are those it was built from (the
    labels' content, not only their shots: a shot redrawn under its id is labelled anew)."""
    from models.evaluate import load_models
    from models.relation_data import build_relation_dataset, read_split

    labels = label_corpus(ws, limits, progress)
    models = load_models(completion_models)
    key = (completion_ours().name, "observed")
    stamp = {"shots": sorted(labels), "labels": labels_digest(labels),
             "completion": models.cards[key]["code_version"] if key in models.cards else "",
             "completion_step": models.cards[key]["step"] if key in models.cards else -1,
             "evidence_points": DEFAULT_PAIRS.evidence_points,
             "pair_features": evidence_digest(), "centres": "solid"}
    out = relations_dir(ws)
    if (out / "stamp.json").exists() and json.loads((out / "stamp.json").read_text()) == stamp:
        return {p.stem: len(read_split(p).labels) for p in sorted(out.glob("*.npz"))}
    shots = read_shots(dataset_dir(ws) / "shots.parquet")
    index = read_index(dataset_dir(ws) / "index.parquet")
    rows = build_relation_dataset(dataset_dir(ws), shots, labels, index, models.models.get(key),
                                  out, DEFAULT_PAIRS, progress=progress)
    (out / "stamp.json").write_text(json.dumps(stamp))
    return rows


def labels_digest(labels: dict[str, ShotLabels]) -> str:
    """SHA-256 over every shot's labelled pairs, views, truth and joints, in shot order."""
    digest = hashlib.sha256()
    for shot in sorted(labels):
        lab = labels[shot]
        digest.update(shot.encode() + b"\0")
        for array in (lab.pairs, lab.views, lab.truth, lab.joints.astype("U16")):
            digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


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
    """Train one method on one input's training split, with its joint head; the best
    checkpoint by validation mean F1 goes to ``out_dir/<method>-<input>.pt``."""
    from models.relation_data import read_split
    from models.relations import RelationConfig
    from models.relations_train import save_relation_checkpoint, train_relations

    train, val = (read_split(relations_dir(ws) / f"{s}.npz") for s in ("train", "val"))
    names = evidence_names(name)
    cfg = RelationConfig(method=method, steps=steps,
                         **{"pair_features": len(names), "evidence": tuple(names),
                            "evidence_gains": evidence_gains(name),
                            "joints": True, **overrides})
    clock = time.perf_counter()
    info = {"input": name, "train_parts": sorted(set(train.meta["part_a"].astype(str))
                                                 | set(train.meta["part_b"].astype(str))),
            "train_pairs": len(train.labels), "val_pairs": len(val.labels),
            "pair_features": names,
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
    from models.relate import PairBatch, decide, load_relation_models
    from models.relation_data import read_split
    from reports.relations import pairs_frame, write_relation_report

    test = read_split(relations_dir(ws) / "test.npz")
    models = load_relation_models(models_dir)
    meta = test.meta
    mm = 1.0 / meta["scale_m_per_mm"].to_numpy(dtype=np.float64)
    keys = [((s, a, v), (s, b, v)) for s, a, b, v in
            zip(meta["scene"], meta["part_a"], meta["part_b"], meta["view"], strict=True)]
    rows = []
    for name in trained():
        reads = INPUTS.get(name).observed_by
        observed = None if reads is None else (test.inputs[reads], test.network_evidence(reads))
        batch = PairBatch(test.inputs[name], mm, keys, test.features[name],
                          test.centres_of(name), tests_for(name), observed)
        for method in RELATION_METHODS.entries():
            out = decide(batch, method, models.models.get((method.name, name)))
            if out is None:
                continue
            rows += _rows(meta, test.labels, name, method.name, *out)
            if progress is not None:
                progress(f"{method.name}/{name}")
    jointed = meta[meta["joint"].astype(str) != "none"]
    joints = jointed[["scene", "part_a", "part_b"]].assign(
        kinematic=jointed["joint"].astype(str)).drop_duplicates()
    return write_relation_report(run_dir, pairs_frame(rows), notes=[
        f"Held-out test split of the training corpus: {len(meta)} pair views of "
        f"{meta['scene'].nunique()} scenes; checkpoints {models.versions()}."], joints=joints)


def _rows(meta: pd.DataFrame, labels: np.ndarray, name: str, method: str, decided: np.ndarray,
          confidence: np.ndarray, broken: np.ndarray, joints: list[str]
          ) -> list[dict[str, Any]]:
    from models.relate import RELATIONS

    records = meta.to_dict("records")
    return [{"scene": m["scene"], "view": int(m["view"]), "part_a": m["part_a"],
             "part_b": m["part_b"], "category": m["category"], "input": name, "method": method,
             "relation": rel, "truth": bool(labels[i, k]), "predicted": bool(decided[i, k]),
             "confidence": float(confidence[i, k]), "near_boundary": bool(m["near_boundary"]),
             "violation": bool(broken[i, k]), "joint": joints[i]}
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


def registered_table() -> pd.DataFrame:
    """The registered relation methods and inputs: kind, name, role, what each is."""
    from models.relation_inputs import INPUTS

    rows = [{"kind": "method", "name": m.name, "role": m.role.value, "what": m.summary}
            for m in RELATION_METHODS.entries()]
    rows += [{"kind": "input", "name": i.name, "role": i.role.value, "what": i.summary}
             for i in INPUTS.entries()]
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
                      "val_f1": round(float(ckpt["metrics"].get("val_f1", np.nan)), 4),
                      "val_joint": round(float(ckpt["metrics"].get("val_joint_balanced",
                                                                   np.nan)), 4),
                      "val_ece": round(float(ckpt["metrics"].get("val_ece_calibrated",
                                                                 np.nan)), 4),
                      "code": ckpt["code_version"]})
    text = "\n".join([
        "# Relation checkpoints", "",
        "The neural-logic relation network `ltn` (a grounding MLP over each part's points "
        "with their distance to the other part as a contact channel, beside the pair's "
        "evidence from fitted primitives (`cadio.evidence.pair_features`: contact planes and "
        "axes, part axes, dominant plane directions, face pairs and coaxial cylinder pairs; "
        "measured on `truth` with the exact normals "
        "of the CAD faces; every network also reads the pair's direction between the parts' "
        "centres and its cone codes, the centres being the centroids of the solids on "
        "`truth` and the points' means elsewhere, and the `truth` networks the `geometric` "
        "tests' four symmetric answers, the coincident one at gain 10, "
        "`models.geometric.network_evidence` and `ANSWER_GAINS`), one Logic Tensor Network "
        "predicate per relation, trained on the labelled facts and the fuzzy-logic axioms) "
        "and `mlp` (the same network on the facts only), one checkpoint per input (`truth`: "
        "CAD surface samples, `partial`: the segmented scan, `completed`: the completion "
        "network's shape). Each relation's decision (threshold and temperature) is fitted on "
        "the validation split and kept in the checkpoint; the best step is chosen by mean F1 "
        "over the relations (`val_joint`: the joint head's balanced accuracy there). The "
        "joint head answers the pair's kinematic joint (none, planar, revolute, "
        "cylindrical, slider), trained on the CAD's joints of the labelled pairs; the report's "
        "joint agreement scores it on the jointed pairs. The networks see the points in the "
        "observer's frame only. Load with `torch.load(weights_only=True)`.", "",
        "## Methods and inputs", "", markdown_table(registered_table()), "",
        "## Checkpoints", "", markdown_table(pd.DataFrame(ckpts)), "",
        "## Data", "", "The pairs of the completion corpus's shots (pair scenes and assemblies "
        "as placed, seeded assembly variants and the training split of the shared multi-part "
        "files), labelled view by view by the truth of placed parts (face mates for "
        "coincident and concentric, dominant plane directions for parallel and "
        "perpendicular); split by part and assembly as the corpus is (the nightly's sample "
        "parts are never trained on).", "",
        markdown_table(dataset_rows(ws)), "",
        "## Training", "", ", ".join(f"{k} {v}" for k, v in config.items()), "",
        f"Held-out report: `{run_dir.name}` of the training workspace.", "",
        (run_dir / "relations.md").read_text(), "", "Trained with:", "", f"    {command}", ""])
    path = out_dir / "MODEL_CARD.md"
    path.write_text(text)
    return path
