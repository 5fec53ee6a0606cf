"""The relation dataset of a corpus: shots labelled view by view by the truth of placed parts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from cadio.cad.ingest import IngestConfig, ingest
from cadio.cad.step import write_step
from cadio.capture.examples import ExampleConfig
from cadio.catalog import read_catalog
from cadio.evidence.pair_features import N_PAIR_FEATURES, PAIR_FEATURES, pair_features_many
from cadio.evidence.pairs import PairConfig
from cadio.records import Relation
from cadio.sandbox import Limits
from cadio.truth.corpus_labels import label_shot
from cadio.truth.relations import directional_truth
from cadio.workspace import Workspace, read_features
from models.checkpoint import build_model
from models.geometric import ALL_EVIDENCE
from models.relation_data import build_relation_dataset, read_split
from models.relations import JOINTS
from models.train import config_for
from models.training.corpus import (
    CorpusConfig,
    assembly_shots,
    build_corpus,
    read_index,
    read_shots,
)
from models.training.relations import label_jobs

CFG = CorpusConfig(example=ExampleConfig(n_in=16, n_out=32), views=2, lengths=())
RELATIONS = [r.value for r in Relation]


@pytest.fixture(scope="module")
def corpus(tmp_path_factory: pytest.TempPathFactory) -> tuple[Workspace, Path]:
    """A pin standing in a holed plate with a block beside it, as one assembly file."""
    import build123d as bd

    lib = tmp_path_factory.mktemp("lib")
    (lib / "assemblies").mkdir()
    plate = bd.Box(60, 40, 4) - bd.Pos(-10, 0, 0) * bd.Cylinder(5, 4)
    pin = bd.Pos(-10, 0, 10) * bd.Cylinder(5, 24)
    block = bd.Pos(15, 0, 7) * bd.Box(20, 20, 10)  # resting on the plate
    write_step(bd.Compound([plate, pin, block]), lib / "assemblies" / "pinned.step")
    ws = Workspace(tmp_path_factory.mktemp("ws"))
    ingest(lib, ws.root, IngestConfig(voxel_sizes=(32,), limits=Limits(workers=2)))
    catalog = read_catalog(ws.catalog)
    ok = catalog[catalog["status"] == "ok"]
    splits = dict.fromkeys(ok["part_id"].astype(str), "train")
    groups = {str(s): "train" for s in ok["source"]}
    out = ws.root / "datasets" / "corpus"
    build_corpus(assembly_shots(catalog, splits, groups, ws.mesh), out, CFG, Limits(workers=2))
    return ws, out


def test_an_assembly_is_labelled_by_its_face_mates_view_by_view(corpus) -> None:  # type: ignore[no-untyped-def]
    ws, out = corpus
    (job,) = label_jobs(ws, read_shots(out / "shots.parquet"))
    labels = label_shot(job)
    assert labels.truth.shape == (len(labels.pairs), 2, 10)
    pairs = {(int(a), int(b)) for a, b in labels.pairs.tolist()}
    # plate 1, pin 2, block 3: the pin is in the plate's bore, the block rests on the plate
    k = {(int(a), int(b)): i for i, (a, b) in enumerate(labels.pairs.tolist())}
    assert (1, 2) in pairs and (1, 3) in pairs
    assert labels.truth[k[(1, 2)], :, RELATIONS.index("concentric")].all()
    assert labels.truth[k[(1, 3)], :, RELATIONS.index("coincident")].all()
    assert not labels.truth[k[(1, 3)], :, RELATIONS.index("concentric")].any()
    # the CAD's joints: the pin turns and slides in its bore, the block slides on the plate
    assert labels.joints[k[(1, 2)]] == "cylindrical" and labels.joints[k[(1, 3)]] == "planar"
    assert labels.joints[k[(2, 3)]] == "none"
    # the directional relations follow each view's camera (the observer's forward axis)
    centre = {p.instance: read_features(Path(p.features_path)).centroid for p in job.parts}
    forward = np.array(job.forward)
    for (a, b), row in k.items():
        for v in range(2):
            side, _ = directional_truth((centre[a] - centre[b])[None], forward[v])
            assert (labels.truth[row, v, :6] == side[0]).all()


def test_the_dataset_holds_every_input_of_every_labelled_pair_view(corpus, tmp_path) -> None:  # type: ignore[no-untyped-def]
    ws, out = corpus
    shots = read_shots(out / "shots.parquet")
    labels = {j.shot: label_shot(j) for j in label_jobs(ws, shots)}
    torch.manual_seed(0)
    model = build_model(config_for("ae", n_in=16, n_out=32, width=4))  # untrained: any shape
    rows = build_relation_dataset(out, shots, labels, read_index(out / "index.parquet"),
                                  model, tmp_path, PairConfig(evidence_points=1500))
    assert rows["train"] > 0
    split = read_split(tmp_path / "train.npz")
    for name in ("truth", "partial", "completed"):
        assert split.inputs[name].shape[1:] == (2, 600, 3)
        assert split.inputs[name].dtype == np.float32
        assert split.features[name].shape == (rows["train"], N_PAIR_FEATURES)
        data = split.data(name)
        assert data.features is not None and np.isfinite(data.features).all()
        assert data.joints is not None
        assert [JOINTS[j] for j in data.joints] == split.meta["joint"].tolist()
    # a network of completed reads the observed points of the same view, and their evidence
    # after the completion's
    own, observed = (split.network_evidence(n) for n in ("completed", "partial"))
    completed = split.data("completed")
    assert completed.features is not None
    assert completed.features.shape == (rows["train"], len(ALL_EVIDENCE))
    np.testing.assert_array_equal(completed.features, np.concatenate([own, observed], axis=1))
    np.testing.assert_array_equal(completed.points, split.inputs["partial"])
    assert {"cylindrical", "planar"} <= set(split.meta["joint"])
    assert set(split.meta["kind"]) == {"assembly"}
    # truth points of a pair are where the parts are: the pin's samples meet the plate's
    gaps = split.features["truth"][:, 0]
    assert gaps.min() < 1.0
    # the evidence of truth and completed is measured on denser clouds than the 600 points
    spacing = PAIR_FEATURES.index("spacing_mm")
    mm = 1.0 / split.meta["scale_m_per_mm"].to_numpy()
    for name in ("truth", "completed"):
        of_points = pair_features_many(split.inputs[name], mm)
        assert np.all(split.features[name][:, spacing] < of_points[:, spacing])
    # partial's is measured on its own points (in the world frame: the fits' rounding differs)
    of_points = pair_features_many(split.inputs["partial"], mm)
    assert np.allclose(split.features["partial"][:, spacing], of_points[:, spacing], rtol=1e-4)
    # truth's centres are the solids' centroids: the directional relations are theirs exactly
    # (the labels' own definition), and they lie among the truth points
    centres = split.centres_of("truth")
    assert centres is not None and centres.shape == (rows["train"], 2, 3)
    assert split.centres_of("partial") is None
    directional, _ = directional_truth((centres[:, 0] - centres[:, 1]) * mm[:, None],
                                       (0.0, 1.0, 0.0))
    assert np.array_equal(directional, split.labels[:, :6])
    lo, hi = split.inputs["truth"].min(axis=2), split.inputs["truth"].max(axis=2)
    assert np.all((centres >= lo) & (centres <= hi))


def test_the_train_flow_trains_and_reports_the_relation_networks(corpus, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The Prefect train flow's relation steps, on the corpus: dataset completed by a
    completion checkpoint, one relation checkpoint, its held-out report and model card."""
    from flows.train import evaluate_relations_task, relation_dataset_task, train_relation_task
    from models.checkpoint import make_checkpoint, save_checkpoint
    from models.relations_train import load_relation_model
    from models.training.config import TrainConfig
    from models.training.relations import relations_dir

    ws, _ = corpus
    torch.manual_seed(0)
    model = build_model(config_for("gan_lstm", n_in=16, n_out=32, width=4))
    completion = tmp_path / "completion"
    save_checkpoint(make_checkpoint(model, 1, {}, {"protocol": "observed"}),
                    completion / "completion-gan_lstm-observed.pt")
    out = tmp_path / "relations"
    cfg = TrainConfig(workspace=str(ws.root), completion_out=str(completion),
                      relation_out=str(out), relation_steps=3, workers=2)
    rows = relation_dataset_task.fn(cfg)
    assert rows["train"] > 0
    folder = relations_dir(ws)
    split_positives = read_split(folder / "train.npz").labels.sum()
    for split in ("val", "test"):  # the fixture's one assembly is all training
        (folder / f"{split}.npz").write_bytes((folder / "train.npz").read_bytes())
    trained = train_relation_task.fn(cfg, "ltn", "completed")
    _, _, ckpt = load_relation_model(Path(trained.path))
    assert ckpt["method"] == "ltn" and ckpt["data"]["input"] == "completed"
    done = evaluate_relations_task.fn(cfg, "train")
    card, run = Path(done.card), Path(done.run_dir)
    assert "ltn" in card.read_text() and (run / "relations.md").exists()
    # the network has a joint head, scored on the split's jointed pairs
    assert ckpt["config"]["joints"] is True and "val_joint" in card.read_text()
    joints = pd.read_csv(run / "assembly_joints.csv")
    assert {"cylindrical", "planar"} <= set(joints["cad_joint"])
    assert set(joints["predicted_joint"]) <= {"none", "planar", "revolute", "cylindrical",
                                              "slider"}
    assert "distinct pairs; 95% interval" in (run / "relations.md").read_text()
    # a rerun with the same labels and completion network reuses the dataset
    stamp = (folder / "stamp.json").stat().st_mtime_ns
    assert relation_dataset_task.fn(cfg) == {
        "test": rows["train"], "train": rows["train"], "val": rows["train"]}
    assert (folder / "stamp.json").stat().st_mtime_ns == stamp
    # a shot labelled anew under its id (a family redrawn) rebuilds it
    labelled = ws.root / "datasets" / "corpus" / "labels"
    (path,) = labelled.glob("*.npz")
    with np.load(path) as z:
        old = {k: z[k] for k in z.files}
    np.savez(path, **{**old, "truth": ~old["truth"]})
    relation_dataset_task.fn(cfg)
    assert (folder / "stamp.json").stat().st_mtime_ns != stamp
    assert read_split(folder / "train.npz").labels.sum() != split_positives


def test_an_assembly_shot_labels_its_distant_pairs_too() -> None:
    """The nightly scores every pair of an assembly, most of them apart: training sees the
    mated pairs first, then every other pair nearest first, up to the budget."""
    from types import SimpleNamespace

    from cadio.truth.corpus_labels import LabelJob, LabelPart, _pairs

    parts = tuple(LabelPart(i, f"p{i}", "x.step", i, "", (0.0,) * 16) for i in range(5))
    job = LabelJob("s", "assembly", parts, (0,), ((0.0, 1.0, 0.0),), max_pairs=9)
    centroids = [np.array([100.0 * i, 0.0, 0.0]) for i in range(5)]

    def contact(i: int, j: int) -> object:
        return SimpleNamespace(coincident=(i, j) == (0, 4), concentric=False)

    pairs = _pairs(job, contact, centroids)
    assert pairs[0] == (0, 4)  # the mated pair first, however far its centroids are
    assert len(pairs) == 9 and len(set(pairs)) == 9  # then the others, up to the budget
    gaps = [abs(i - j) for i, j in pairs[1:]]
    assert gaps == sorted(gaps) and gaps[-1] == 3  # nearest first, distant ones included
