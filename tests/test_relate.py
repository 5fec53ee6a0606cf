"""The relation stage's harness: every method on every input of real captures, in one table."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from cadio.cad.ingest import IngestConfig, ingest
from cadio.cad.step import write_step
from cadio.capture.scan import ScanConfig, capture_scenes
from cadio.catalog import read_catalog
from cadio.sandbox import Limits
from cadio.truth.scene_config import SceneConfig
from cadio.truth.scenes import generate_scenes, read_scene_parts
from cadio.workspace import Workspace
from models.evaluate import SHIPPED
from models.relate import SHIPPED_RELATIONS, relate_batch, relate_isolated
from models.relation_methods import RELATION_METHODS
from models.relations import RelationConfig
from models.relations_train import save_relation_checkpoint, train_relations
from models.synthetic import relation_pairs
from reports.relations import PAIR_COLUMNS

# The shipped completion network reads 32^3 views: the captures make single observed views.
CFG = ScanConfig(views_per_scene=2, lengths=(), protocols=("observed",))


@pytest.fixture(scope="module")
def ws(tmp_path_factory: pytest.TempPathFactory) -> Workspace:
    import build123d as bd

    lib = tmp_path_factory.mktemp("lib")
    (lib / "parts").mkdir()
    write_step(bd.Box(30, 20, 10), lib / "parts" / "block.step")
    write_step(bd.Cylinder(6, 30), lib / "parts" / "pin.step")
    space = Workspace(tmp_path_factory.mktemp("ws"))
    ingest(lib, space.root, IngestConfig(voxel_sizes=(32,), limits=Limits(workers=1)))
    parts = read_scene_parts(read_catalog(space.catalog), space.root)
    scenes = generate_scenes(parts, SceneConfig(pairs_per_relation=1, val_fraction=0.0,
                                                test_fraction=0.0))
    captured = capture_scenes(scenes.head(2), read_catalog(space.catalog), space, CFG)
    from cadio.capture.scan import with_inputs

    assert all(not with_inputs(c, space, CFG).error for c in captured)
    return space


def _checkpoints(folder: Path, train_parts: list[str]) -> Path:
    """Tiny ltn and mlp networks for every input (trained a few steps on synthetic pairs)."""
    torch.set_num_threads(1)
    data = relation_pairs(32, n_points=64, seed=3)
    for method in ("ltn", "mlp"):
        cfg = RelationConfig(method=method, steps=4, batch_size=8, eval_every=4,
                             train_points=32, widths=(8, 8, 8, 8), embed=8, ntn_k=2)
        for name in ("truth", "partial", "completed"):
            res = train_relations(cfg, data, data, data_info={"input": name,
                                                               "train_parts": train_parts})
            save_relation_checkpoint(folder / f"{method}-{name}.pt", res.checkpoint)
    return folder


def test_every_method_decides_every_input_of_every_pair_view(ws: Workspace,
                                                             tmp_path: Path) -> None:
    models = _checkpoints(tmp_path / "models", [])
    captures = sorted(ws.root.glob("captures/*.mcap"))
    batch = relate_isolated(captures, ws, models, SHIPPED, tmp_path / "rows.parquet")  # as the
    assert batch.failed == () and batch.captures == 2  # night runs it: in a worker process
    rows = pd.read_parquet(batch.path)
    assert tuple(rows.columns[:len(PAIR_COLUMNS)]) == PAIR_COLUMNS
    assert set(rows["method"]) == set(RELATION_METHODS.names())
    assert set(rows["input"]) == {"truth", "partial", "completed"}
    per_view = rows.groupby(["scene", "view", "input", "method"]).size()
    assert (per_view == 10).all() and batch.pair_views == 4  # 2 scenes x 2 views
    # the truth of a pair view does not depend on the input or the method that is scored
    truth = rows.pivot_table(index=["scene", "view", "relation"], columns=["input", "method"],
                             values="truth")
    assert (truth.nunique(axis=1) == 1).all()
    learned = rows[rows["method"] != "geometric"]
    assert learned["confidence"].between(0, 1).all()
    assert rows.loc[rows["method"] == "geometric", "confidence"].isna().all()


def test_pairs_of_parts_a_network_trained_on_are_left_out(ws: Workspace, tmp_path: Path) -> None:
    captures = sorted(ws.root.glob("captures/*.mcap"))
    seen = [str(p) for p in read_catalog(ws.catalog)["part_id"]]
    models = _checkpoints(tmp_path / "models", seen)
    batch = relate_batch(captures, ws, models, SHIPPED, tmp_path / "rows.parquet")
    assert batch.rows == 0 and len(pd.read_parquet(batch.path)) == 0
    # counted, so that the report can say why a night of training parts scored no pair
    everything = relate_batch(captures, ws, SHIPPED_RELATIONS, SHIPPED, tmp_path / "all.parquet")
    assert everything.left_out == 0 and everything.pair_views > 0
    assert batch.left_out == everything.pair_views and batch.pair_views == 0


def test_a_broken_capture_is_reported_and_the_others_go_on(ws: Workspace,
                                                           tmp_path: Path) -> None:
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"\x89MCAP0\r\n not really")
    captures = [broken, *sorted(ws.root.glob("captures/*.mcap"))]
    batch = relate_batch(captures, ws, tmp_path / "none", SHIPPED, tmp_path / "rows.parquet",
                         )
    assert len(batch.failed) == 1 and "broken.mcap" in batch.failed[0]
    rows = pd.read_parquet(batch.path)
    assert set(rows["method"]) == {"geometric"} and np.all(rows["view"] >= 0)


def test_a_checkpoint_that_does_not_load_is_reported_and_the_baseline_runs(
        ws: Workspace, tmp_path: Path) -> None:
    folder = tmp_path / "models"
    folder.mkdir()
    (folder / "ltn-partial.pt").write_bytes(b"not a checkpoint")
    captures = sorted(ws.root.glob("captures/*.mcap"))
    batch = relate_batch(captures, ws, folder, SHIPPED, tmp_path / "rows.parquet")
    assert len(batch.failed) == 1 and batch.failed[0].startswith("ltn-partial.pt: ")
    assert set(pd.read_parquet(batch.path)["method"]) == {"geometric"}


def test_a_checkpoint_trained_on_other_pair_evidence_is_left_out_with_the_reason(
        ws: Workspace, tmp_path: Path) -> None:
    """A network trained on an older pair evidence vector would read new numbers with old
    meanings (or fail mid-batch on the width): it is left out at load, with what to do."""
    import dataclasses

    torch.set_num_threads(1)
    data = relation_pairs(16, n_points=64, seed=3)
    data = dataclasses.replace(data, features=np.zeros((16, 5), dtype=np.float32))
    cfg = RelationConfig(method="ltn", steps=2, batch_size=8, eval_every=2, train_points=32,
                         widths=(8, 8, 8, 8), embed=8, ntn_k=2, pair_features=5)
    folder = tmp_path / "models"
    res = train_relations(cfg, data, data, data_info={"input": "partial", "train_parts": []})
    save_relation_checkpoint(folder / "ltn-partial.pt", res.checkpoint)
    captures = sorted(ws.root.glob("captures/*.mcap"))
    batch = relate_batch(captures, ws, folder, SHIPPED, tmp_path / "rows.parquet")
    assert len(batch.failed) == 1 and batch.failed[0].startswith("ltn-partial.pt: trained on 5")
    assert "retrain" in batch.failed[0]
    assert set(pd.read_parquet(batch.path)["method"]) == {"geometric"}


def test_a_network_reads_the_geometric_answers_when_its_checkpoint_lists_them(
        ws: Workspace, tmp_path: Path) -> None:
    """A checkpoint that lists the tests' answers after the evidence reads them (the width of
    both); one trained on the evidence alone reads its first columns, as before."""
    import dataclasses

    from cadio.evidence.pair_features import N_PAIR_FEATURES, PAIR_FEATURES
    from models.geometric import GEOMETRIC_ANSWERS

    torch.set_num_threads(1)
    data = relation_pairs(16, n_points=64, seed=3)
    width = N_PAIR_FEATURES + len(GEOMETRIC_ANSWERS)
    rng = np.random.default_rng(0)
    data = dataclasses.replace(data, features=rng.random((16, width), dtype=np.float32))
    folder = tmp_path / "models"
    for name, names in (("truth", [*PAIR_FEATURES, *GEOMETRIC_ANSWERS]),
                        ("partial", list(PAIR_FEATURES))):
        cfg = RelationConfig(method="ltn", steps=2, batch_size=8, eval_every=2,
                             train_points=32, widths=(8, 8, 8, 8), embed=8, ntn_k=2,
                             pair_features=len(names))
        res = train_relations(cfg, data, data, data_info={"input": name, "train_parts": [],
                                                           "pair_features": names})
        save_relation_checkpoint(folder / f"ltn-{name}.pt", res.checkpoint)
    captures = sorted(ws.root.glob("captures/*.mcap"))
    batch = relate_batch(captures, ws, folder, SHIPPED, tmp_path / "rows.parquet")
    assert batch.failed == ()
    rows = pd.read_parquet(batch.path)
    assert set(rows.loc[rows["method"] == "ltn", "input"]) == {"truth", "partial"}


def test_the_completed_input_is_the_same_where_the_parts_are_not_scored(
        ws: Workspace, tmp_path: Path) -> None:
    """A capture that scores none of its parts keeps only each view's observed input: the
    relation stage completes exactly what it completes from the full examples."""
    from cadio.capture.scan import scan_inputs
    from models.evaluate import load_models
    from models.relation_inputs.completed import completions_of

    light = Workspace(tmp_path / "ws")
    shutil.copytree(ws.root, light.root)
    model = load_models(SHIPPED).models[("gan_lstm", "observed")]
    for capture in sorted(light.root.glob("captures/*.mcap")):
        full = completions_of(capture, light, model)
        assert scan_inputs(capture, light, CFG, scored=()).examples == 0
        again = completions_of(capture, light, model)
        assert full.keys() == again.keys() and full
        assert all(np.array_equal(full[k], again[k]) for k in full)


def test_a_checkpoint_naming_its_columns_reads_them_after_evidence_is_appended() -> None:
    """The evidence is only ever appended to: a shipped network trained before the coaxial
    columns names the columns it reads, so it still loads and reads exactly those."""
    from cadio.evidence.pair_features import PAIR_FEATURES
    from models.relate import load_relation_models

    models = load_relation_models(SHIPPED_RELATIONS)
    assert models.errors == ()
    names = models.cards[("ltn", "partial")]["data"]["pair_features"]
    assert "coax_face_gap_mm" in PAIR_FEATURES and "coax_face_gap_mm" not in names


def test_a_completed_network_is_handed_the_observed_points_evidence_of_each_view(
        ws: Workspace, tmp_path: Path) -> None:
    """A ``completed`` network trained on its own evidence and the observed points' (the
    width of both) decides every completed pair view of a night, beside the baseline."""
    import dataclasses

    from models.geometric import ALL_EVIDENCE, evidence_names

    torch.set_num_threads(1)
    names = evidence_names("completed")
    data = relation_pairs(16, n_points=64, seed=3)
    rng = np.random.default_rng(0)
    data = dataclasses.replace(data, features=rng.random((16, len(ALL_EVIDENCE)),
                                                         dtype=np.float32))
    cfg = RelationConfig(method="ltn", steps=2, batch_size=8, eval_every=2, train_points=32,
                         widths=(8, 8, 8, 8), embed=8, ntn_k=2, pair_features=len(names),
                         evidence=tuple(names))
    res = train_relations(cfg, data, data, data_info={"input": "completed", "train_parts": [],
                                                       "pair_features": names})
    save_relation_checkpoint(tmp_path / "models" / "ltn-completed.pt", res.checkpoint)
    captures = sorted(ws.root.glob("captures/*.mcap"))
    batch = relate_batch(captures, ws, tmp_path / "models", SHIPPED, tmp_path / "rows.parquet")
    assert batch.failed == ()
    rows = pd.read_parquet(batch.path)
    ltn = rows[rows["method"] == "ltn"]
    assert set(ltn["input"]) == {"completed"}
    completed = rows[rows["input"] == "completed"]
    assert len(ltn) == len(completed[completed["method"] == "geometric"]) > 0


def test_a_relation_worker_that_dies_fails_its_captures_not_the_night(ws: Workspace,
                                                                      tmp_path: Path) -> None:
    from cadio.sandbox import Limits

    captures = sorted(ws.root.glob("captures/*.mcap"))
    batch = relate_isolated(captures, ws, SHIPPED_RELATIONS, SHIPPED, tmp_path / "rows.parquet",
                            Limits(seconds=0.5, workers=1))
    assert batch.rows == 0 and not (tmp_path / "rows.parquet").exists()
    assert [f.split(":")[0] for f in batch.failed] == [c.name for c in captures]
    assert all("relation worker" in f and "time" in f for f in batch.failed)


def test_evidence_within_a_pose_s_uncertainty_reads_its_lengths_less_the_slack() -> None:
    from cadio.evidence.pair_features import FAR_MM, PAIR_FEATURES
    from models.geometric import POSE_LENGTHS, within_pose

    col = {n: PAIR_FEATURES.index(n) for n in PAIR_FEATURES}
    raw = np.full((3, len(PAIR_FEATURES)), 2.0, dtype=np.float32)
    raw[:, col["face_offset_mm"]] = (0.4, 3.0, FAR_MM)  # the third pair: no face pair found
    out = within_pose(raw, [0.5, 1.0, 1.0])
    assert out[:, col["face_offset_mm"]].tolist() == [0.0, 2.0, FAR_MM]
    assert out[:, col["gap_mm"]].tolist() == [1.5, 1.0, 1.0]
    others = [i for n, i in col.items() if n not in POSE_LENGTHS]
    np.testing.assert_array_equal(out[:, others], raw[:, others])  # radii, angles: as measured
    np.testing.assert_array_equal(within_pose(raw, np.zeros(3)), raw)


def test_evidence_within_a_pose_s_turn_reads_its_dominant_directions_nearer_to_aligned_or_square(
        ) -> None:
    from cadio.evidence.pair_features import PAIR_FEATURES
    from models.geometric import POSE_LENGTHS, within_pose

    col = {n: PAIR_FEATURES.index(n) for n in PAIR_FEATURES}
    raw = np.full((3, len(PAIR_FEATURES)), 2.0, dtype=np.float32)
    raw[:, col["dom_angle_deg"]] = (5.0, 84.0, 45.0)
    raw[:, col["face_angle_deg"]] = (5.0, 1.0, 30.0)
    out = within_pose(raw, np.zeros(3), [4.0, 4.0, 0.0])
    assert out[:, col["dom_angle_deg"]].tolist() == [1.0, 88.0, 45.0]  # parallel, square
    others = [i for n, i in col.items() if n not in (*POSE_LENGTHS, "dom_angle_deg")]
    np.testing.assert_array_equal(out[:, others], raw[:, others])


def test_a_change_to_the_code_reading_pair_views_changes_the_relations_cache_key(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import models.geometric
    from models.relate import reading_digest

    before = reading_digest()
    changed = tmp_path / "geometric.py"
    changed.write_bytes(Path(models.geometric.__file__).read_bytes() + b"\n# a tolerance\n")
    monkeypatch.setattr(models.geometric, "__file__", str(changed))
    assert reading_digest() != before


def test_a_network_decides_a_repeated_pair_view_once_and_answers_each_alike() -> None:
    """An exact input's pair shows the same clouds in every view: the network decides each
    distinct one once, and every repeat gets its answers (decisions, confidences, joints)."""
    from models.relate import PairBatch, decide, distinct_rows, load_relation_models

    torch.set_num_threads(1)
    data = relation_pairs(3, n_points=64, seed=5)
    model = load_relation_models(SHIPPED_RELATIONS).models[("ltn", "truth")]
    order = [0, 1, 0, 2, 1, 0]
    first, back = distinct_rows(data.points[order], data.mm[order])
    assert first.tolist() == [0, 1, 3] and back.tolist() == [0, 1, 0, 2, 1, 0]
    repeated = decide(PairBatch(data.points[order], data.mm[order]), "ltn", model)
    once = decide(PairBatch(data.points, data.mm), "ltn", model)
    assert repeated is not None and once is not None
    for got, want in zip(repeated[:3], once[:3], strict=True):
        assert np.array_equal(got, want[order], equal_nan=got.dtype.kind == "f")
    assert list(repeated[3]) == [once[3][i] for i in order]
