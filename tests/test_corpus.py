"""The training corpus: parts alone, in pairs and in assemblies, cut into the nightly's inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cadio.cad.ingest import IngestConfig, ingest
from cadio.cad.step import write_step
from cadio.capture.examples import ExampleConfig, read_example
from cadio.catalog import read_catalog
from cadio.sandbox import Limits
from cadio.truth.scene_config import SceneConfig
from cadio.truth.scenes import generate_scenes, read_scene_parts
from cadio.workspace import Workspace
from models.training.corpus import (
    CorpusConfig,
    alone_shots,
    assembly_shots,
    build_corpus,
    corpus_splits,
    pair_shots,
    read_index,
    read_shots,
)

CFG = CorpusConfig(example=ExampleConfig(n_in=16, n_out=32), views=2, lengths=(2,))


@pytest.fixture(scope="module")
def ws(tmp_path_factory: pytest.TempPathFactory) -> Workspace:
    import build123d as bd

    lib = tmp_path_factory.mktemp("lib")
    (lib / "fasteners").mkdir()
    (lib / "assemblies").mkdir()
    write_step(bd.Cylinder(4, 30), lib / "fasteners" / "pin.step")
    write_step(bd.Box(40, 40, 4) - bd.Cylinder(5, 4), lib / "fasteners" / "plate.step")
    # a pin standing in a holed plate: two solids of one file, as placed
    plate = bd.Box(40, 40, 4) - bd.Cylinder(5, 4)
    pin = bd.Pos(0, 0, 10) * bd.Cylinder(5, 24)
    write_step(bd.Compound([plate, pin]), lib / "assemblies" / "pinned.step")
    space = Workspace(tmp_path_factory.mktemp("ws"))
    ingest(lib, space.root, IngestConfig(voxel_sizes=(32,), limits=Limits(workers=2)))
    return space




def test_a_shape_held_out_anywhere_is_held_out_everywhere() -> None:
    groups = {"a.step": ["p1", "p2"], "b.step": ["p3"], "c.step": ["p4"]}
    shape_of = {"p1": "bolt", "p3": "bolt", "p2": "nut", "p4": "plate"}
    group_split, part_split = corpus_splits(
        groups, shape_of, fractions=lambda g: (0.0, 1.0) if g == "b.step" else (0.0, 0.0))
    assert group_split["b.step"] == "test"
    assert part_split["p1"] == part_split["p3"] == "test"  # the same bolt geometry
    assert set(part_split) == {"p1", "p2", "p3", "p4"}
    assert part_split["p2"] == part_split["p4"] == "train"


def test_shots_of_three_kinds_give_examples_and_relation_inputs(ws: Workspace,
                                                                 tmp_path: Path) -> None:
    catalog = read_catalog(ws.catalog)
    ok = catalog[catalog["status"] == "ok"]
    assert len(ok) == 4
    splits = dict.fromkeys(ok["part_id"].astype(str), "train")
    groups = {str(s): "train" for s in ok["source"]}
    alone = alone_shots(ok[ok["n_solids"] == 1], splits, ws.mesh)
    scenes = generate_scenes(read_scene_parts(catalog, ws.root),
                             SceneConfig(pairs_per_relation=1, val_fraction=0.0,
                                         test_fraction=0.0))
    pairs = pair_shots(scenes.head(2), splits, ws.mesh)
    assembly = assembly_shots(catalog, splits, groups, ws.mesh)
    assert len(alone) == 2 and len(pairs) == 2 and len(assembly) == 1
    assert len(assembly[0].parts) == 2
    shots = [*alone, *pairs, *assembly]
    index = build_corpus(shots, tmp_path, CFG, Limits(workers=2))
    ok_rows = index[index["status"] == "ok"]
    assert set(ok_rows["kind"]) == {"alone", "pair", "assembly"}
    assert set(ok_rows["n_views"]) == {1, 2}
    for row in ok_rows.itertuples():
        example = read_example(tmp_path / str(row.file))
        assert example.inputs.shape == (row.n_views, 2, 16, 16, 16)
        assert example.target is not None and example.target.any()
        assert example.meta["shot"] == row.shot and example.meta["part_id"] == row.part_id
    # the relation inputs of the assembly: both instances in each view they show, and their
    # CAD surface samples where the instances really are (near their observed points)
    with np.load(tmp_path / "views" / f"{assembly[0].shot_id}.npz") as z:
        assert sorted(set(z["instance"].tolist())) == [1, 2]
        assert z["partial"].shape[1:] == (600, 3) and z["truth"].shape == (2, 600, 3)
        first = z["partial"][z["instance"] == 2][0]
        truth = z["truth"][list(z["truth_instance"]).index(2)]
        gap = np.linalg.norm(first[:, None] - truth[None], axis=2).min(axis=1)
        assert np.median(gap) < 0.005  # metres: the seen pin lies on the pin's CAD surface
    assert [s.shot_id for s in read_shots(tmp_path / "shots.parquet")] == [
        s.shot_id for s in shots]
    again = build_corpus(shots, tmp_path, CFG, Limits(workers=2))  # nothing left to render
    assert len(again) == len(index)
    # a scene drawn anew under its id is a new shot; the old one leaves the index and the
    # shot table (by id alone, the corpus kept the renders of the old placement)
    moved = scenes.head(1).copy()
    moved["pose_b"] = [list(np.asarray(moved["pose_b"].iloc[0]) + np.r_[[0.0] * 3, 1.0,
                                                                         [0.0] * 12])]
    redrawn = pair_shots(moved, splits, ws.mesh)[0]
    assert redrawn.group == pairs[0].group and redrawn.shot_id != pairs[0].shot_id
    assert pair_shots(scenes.head(1), splits, ws.mesh)[0].shot_id == pairs[0].shot_id
    later = build_corpus([*alone, redrawn, pairs[1], *assembly], tmp_path, CFG,
                         Limits(workers=2))
    assert pairs[0].shot_id not in set(later["shot"]) and redrawn.shot_id in set(later["shot"])
    assert len(later) == len(index) - (index["shot"] == pairs[0].shot_id).sum() + (
        later["shot"] == redrawn.shot_id).sum()
    assert [s.shot_id for s in read_shots(tmp_path / "shots.parquet")] == [
        s.shot_id for s in (*alone, redrawn, pairs[1], *assembly)]


def test_an_instance_of_another_split_gives_no_example(ws: Workspace, tmp_path: Path) -> None:
    """A training assembly holding a test part: the test part's views stay out."""
    catalog = read_catalog(ws.catalog)
    ok = catalog[(catalog["status"] == "ok") & (catalog["n_solids"] == 2)]
    held = str(ok.sort_values("solid_index")["part_id"].iloc[0])
    splits = {str(p): ("test" if str(p) == held else "train") for p in ok["part_id"]}
    groups = {str(s): "train" for s in ok["source"]}
    index = build_corpus(assembly_shots(catalog, splits, groups, ws.mesh), tmp_path, CFG,
                         Limits(workers=2))
    examples = index[index["status"] == "ok"]
    assert len(examples) and held not in set(examples["part_id"])
    assert set(examples["split"]) == {"train"}


def test_a_corpus_of_another_configuration_is_refused(tmp_path: Path) -> None:
    build_corpus([], tmp_path, CFG)
    with pytest.raises(ValueError, match="another folder"):
        build_corpus([], tmp_path, CorpusConfig(views=3))
    assert isinstance(read_index(tmp_path / "index.parquet"), pd.DataFrame)
