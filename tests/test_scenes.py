"""Tests of cadio.truth.scenes: labels from ``relate``, intent, boundaries, part splits, contact."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import SHARED_STEP_DIR
from test_relations import box_features, cylinder_features

from cadio.records import Features, Relation
from cadio.tolerances import DEFAULT_TOLERANCES as TOL
from cadio.truth.relations import relation_table
from cadio.truth.scenes import (
    SPLITS,
    SceneConfig,
    ScenePart,
    assign_splits,
    generate_scenes,
    is_eligible,
    label_pair,
    read_scenes,
    scene_poses,
    write_scenes,
)

log = logging.getLogger(__name__)
NAMES = [r.value for r in Relation]
FASTENERS = SHARED_STEP_DIR / "fasteners"


def synthetic_parts(n: int = 30, seed: int = 0) -> list[ScenePart]:
    rng = np.random.default_rng(seed)
    parts = []
    for i in range(n):
        if i % 2:
            f = box_features(tuple(rng.uniform(5, 80, 3)))
            parts.append(ScenePart(f"box-{i:02d}", "brakes-clutches-couplings", f))
        else:
            f = cylinder_features(rng.uniform(2, 20), rng.uniform(5, 80))
            parts.append(ScenePart(f"cyl-{i:02d}", "fasteners", f))
    return parts


CFG = SceneConfig(seed=5, pairs_per_relation=60, near_boundary_fraction=0.2)


@pytest.fixture(scope="module")
def parts() -> list[ScenePart]:
    return synthetic_parts()


@pytest.fixture(scope="module")
def scenes(parts: list[ScenePart]) -> pd.DataFrame:
    return generate_scenes(parts, CFG)


def _holds_intended(df: pd.DataFrame) -> pd.Series:
    return df.apply(lambda row: bool(row[row["intended"]]), axis=1)


def _check_labels(df: pd.DataFrame, parts: list[ScenePart], cfg: SceneConfig) -> None:
    by_id = {p.part_id: p.features for p in parts}
    for _, row in df.iterrows():
        pose_a, pose_b = scene_poses(row)
        result = label_pair(by_id[row["part_a"]], by_id[row["part_b"]], pose_a, pose_b, cfg)
        assert relation_table(result) == {k: bool(row[k]) for k in NAMES}, row["scene_id"]


def _penetration_mm(a: Features, b: Features) -> float:
    """Depth (mm) by which two axis-aligned boxes interpenetrate; <= 0 when apart."""
    depth = np.minimum(a.bbox_max, b.bbox_max) - np.maximum(a.bbox_min, b.bbox_min)
    return float(depth.min())


def _check_apart(df: pd.DataFrame, parts: list[ScenePart]) -> None:
    by_id = {p.part_id: p.features for p in parts}
    for _, row in df.iterrows():
        pose_a, pose_b = scene_poses(row)
        depth = _penetration_mm(by_id[row["part_a"]].transformed(pose_a),
                                by_id[row["part_b"]].transformed(pose_b))
        allowed = TOL.coplanar_mm if row["intended"] == "coincident" else 1e-9
        assert depth <= allowed, (row["scene_id"], depth)


def test_table_shape_and_balance(scenes: pd.DataFrame) -> None:
    for col in ["scene_id", "split", "part_a", "part_b", "category_a", "category_b", "pose_a",
                "pose_b", "intended", "near_boundary", *NAMES]:
        assert col in scenes.columns
    assert scenes.scene_id.is_unique
    assert all(len(p) == 16 for p in scenes.pose_a)
    counts = scenes.groupby(["split", "intended"]).size().unstack()
    assert (counts.nunique(axis=1) == 1).all(), counts  # balanced within each split
    assert counts.sum().tolist() == [CFG.pairs_per_relation] * len(Relation)
    assert scenes[NAMES].dtypes.eq(bool).all()


def test_labels_are_relate_on_the_poses(scenes: pd.DataFrame, parts: list[ScenePart]) -> None:
    _check_labels(scenes, parts, CFG)


def test_intended_relation_holds_in_plain_scenes(scenes: pd.DataFrame) -> None:
    plain = scenes[~scenes.near_boundary]
    fraction = _holds_intended(plain).mean()
    log.info("intended relation holds in %.4f of %d plain scenes", fraction, len(plain))
    assert fraction >= 0.99, fraction


def test_near_boundary_pairs_straddle_the_rule(scenes: pd.DataFrame) -> None:
    near = scenes[scenes.near_boundary]
    assert set(near.near_side) == {"inside", "outside"}
    assert set(near.intended) == set(NAMES)
    holds = _holds_intended(near)
    assert (holds == (near.near_side == "inside")).all()
    directional = near[near.intended.isin(NAMES[:6])]
    assert not directional[directional.near_side == "outside"][NAMES[:6]].any(axis=None)


def test_same_seed_same_scenes_other_seed_other(parts: list[ScenePart],
                                                scenes: pd.DataFrame) -> None:
    again = generate_scenes(list(reversed(parts)), CFG)  # input order does not matter
    pd.testing.assert_frame_equal(scenes, again)
    other = generate_scenes(parts, replace(CFG, seed=6))
    assert other.pose_a.tolist() != scenes.pose_a.tolist()


def test_splits_are_by_part(scenes: pd.DataFrame, parts: list[ScenePart]) -> None:
    split_of = assign_splits([p.part_id for p in parts], CFG.seed, CFG.val_fraction,
                             CFG.test_fraction)
    assert set(scenes.split) == set(SPLITS)
    for split in SPLITS:
        rows = scenes[scenes.split == split]
        used = set(rows.part_a) | set(rows.part_b)
        assert all(split_of[p] == split for p in used)
    # a part keeps its split when the catalog grows
    more = assign_splits([*split_of, "new-part"], CFG.seed, CFG.val_fraction, CFG.test_fraction)
    assert all(more[p] == s for p, s in split_of.items())


def test_no_interpenetration_except_coincident_contact(scenes: pd.DataFrame,
                                                       parts: list[ScenePart]) -> None:
    _check_apart(scenes, parts)
    assert (scenes.part_a != scenes.part_b).all()


def test_a_part_is_never_paired_with_itself() -> None:
    """A pool of one part for a relation gives no scene for it (two instances of one part
    would be one part to every later stage), and no scene pairs a part with itself."""
    parts = [ScenePart("box", "x", box_features((40.0, 30.0, 5.0))),
             ScenePart("cyl", "x", cylinder_features(5.0, 30.0))]
    cfg = replace(CFG, pairs_per_relation=8, val_fraction=0.0, test_fraction=0.0)
    df = generate_scenes(parts, cfg)
    assert (df.part_a != df.part_b).all()
    assert "concentric" not in set(df.intended)  # only the cylinder has an axis
    assert set(df.intended) >= {r.value for r in Relation if r is not Relation.CONCENTRIC}


def test_coincident_side_by_side_when_faces_are_not_extreme() -> None:
    """Plates with domes above and below their flat faces cannot stack face to face."""
    plate = box_features((60.0, 40.0, 4.0))
    domed = replace(plate, bbox_min=np.array([-30.0, -20.0, -9.0]),
                    bbox_max=np.array([30.0, 20.0, 9.0]))
    parts = [ScenePart(f"domed-{i}", "x", domed) for i in range(6)]
    cfg = replace(CFG, pairs_per_relation=20, near_boundary_fraction=0.0,
                  val_fraction=0.0, test_fraction=0.0)
    df = generate_scenes(parts, cfg)
    df = df[df.intended == "coincident"]
    assert df.coincident.all() and not df.parallel.any()
    _check_apart(df, parts)
    _check_labels(df, parts, cfg)


def test_eligibility_follows_the_paper(parts: list[ScenePart], scenes: pd.DataFrame) -> None:
    conc = scenes[scenes.intended == "concentric"]
    assert set(conc.part_a) | set(conc.part_b) <= {p.part_id for p in parts
                                                    if p.features.principal_axis is not None}
    bare = ScenePart("bare", "x", replace(box_features(), planes=(), principal_plane=None))
    assert is_eligible(bare, Relation.LEFT, CFG)
    assert not is_eligible(bare, Relation.PARALLEL, CFG)
    assert not is_eligible(bare, Relation.CONCENTRIC, CFG)


def test_write_read_round_trip(scenes: pd.DataFrame, tmp_path: Path) -> None:
    path = tmp_path / "scenes.parquet"
    write_scenes(path, scenes)
    back = read_scenes(path)
    pd.testing.assert_frame_equal(back, scenes)
    assert back.attrs["config"]["tolerances"]["coplanar_mm"] == TOL.coplanar_mm
    assert back.attrs["config"]["seed"] == CFG.seed
    assert not list(tmp_path.glob(".*tmp"))


def test_bad_inputs_are_refused(parts: list[ScenePart]) -> None:
    with pytest.raises(ValueError):
        generate_scenes([*parts, parts[0]], CFG)
    with pytest.raises(ValueError):
        generate_scenes(parts, replace(CFG, test_fraction=0.8, val_fraction=0.5))


@pytest.mark.shared
def test_real_fasteners(tmp_path: Path) -> None:
    if not FASTENERS.is_dir():
        pytest.skip("shared STEP data absent")
    build123d = pytest.importorskip("build123d")
    features = pytest.importorskip("cadio.cad.features")
    parts = [
        ScenePart(p.name, "fasteners",
                  features.extract_features(build123d.import_step(p).solids()[0].wrapped))
        for p in sorted(FASTENERS.iterdir())
    ]
    cfg = SceneConfig(seed=1, pairs_per_relation=30, near_boundary_fraction=0.2,
                      val_fraction=0.0, test_fraction=0.3)
    df = generate_scenes(parts, cfg)
    assert len(df) > 0
    _check_labels(df, parts, cfg)
    _check_apart(df, parts)
    plain = df[~df.near_boundary]
    fraction = _holds_intended(plain).mean()
    log.info("real fasteners: intended holds in %.4f of %d plain scenes", fraction, len(plain))
    assert fraction >= 0.99
    near = df[df.near_boundary]
    assert (_holds_intended(near) == (near.near_side == "inside")).all()
