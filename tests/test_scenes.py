"""Tests of cadio.truth.scenes: labels from the truth, intent, boundaries, part splits, contact."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import build123d as bd
import numpy as np
import pandas as pd
import pytest
from conftest import SHARED_STEP_DIR

from cadio.records import Relation
from cadio.tolerances import DEFAULT_TOLERANCES as TOL
from cadio.truth.placement import exact_gap, interfere
from cadio.truth.relations import relation_table
from cadio.truth.scene_config import SceneConfig, night_scene_config
from cadio.truth.scenes import (
    CLEARANCE,
    CONTACT,
    SPLITS,
    ScenePart,
    assign_splits,
    generate_scenes,
    is_eligible,
    label_pair,
    read_scenes,
    scene_part,
    scene_poses,
    scenes_stamp,
    write_scenes,
)
from reports.tables import scenes_table

log = logging.getLogger(__name__)
NAMES = [r.value for r in Relation]
FASTENERS = SHARED_STEP_DIR / "fasteners"


def synthetic_parts(n: int = 30, seed: int = 0) -> list[ScenePart]:
    """Plates and blocks, pins, and rings whose bores fit some pins (the sizes of a fastener
    library: radii in steps of 0.5 mm)."""
    rng = np.random.default_rng(seed)
    parts = []
    for i in range(n):
        if i % 3 == 0:
            shape = bd.Box(*rng.uniform(5, 80, 3))
            parts.append(scene_part(f"box-{i:02d}", "brakes-clutches-couplings", shape.wrapped))
        elif i % 3 == 1:
            r = 0.5 * int(rng.integers(4, 20))
            shape = bd.Cylinder(r, rng.uniform(5, 60))
            parts.append(scene_part(f"pin-{i:02d}", "fasteners", shape.wrapped))
        else:
            bore = 0.5 * int(rng.integers(4, 20)) + rng.uniform(0.0, 0.5)
            shape = bd.Cylinder(bore + rng.uniform(2, 10), rng.uniform(2, 20)) - \
                bd.Cylinder(bore, 60)
            parts.append(scene_part(f"ring-{i:02d}", "linear-rotary-motion", shape.wrapped))
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
    by_id = {p.part_id: p for p in parts}
    for _, row in df.iterrows():
        pose_a, pose_b = scene_poses(row)
        result = label_pair(by_id[row["part_a"]], by_id[row["part_b"]], pose_a, pose_b, cfg)
        assert relation_table(result) == {k: bool(row[k]) for k in NAMES}, row["scene_id"]


def _check_apart(df: pd.DataFrame, parts: list[ScenePart]) -> None:
    """No two placed parts share volume (an exact Boolean): they touch at most."""
    by_id = {p.part_id: p for p in parts}
    for _, row in df.iterrows():
        pose_a, pose_b = scene_poses(row)
        assert not interfere(by_id[row["part_a"]].model, pose_a, by_id[row["part_b"]].model,
                             pose_b), row["scene_id"]


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


def _unmatched(df: pd.DataFrame) -> pd.Series:
    """Concentric pairs of the split whose parts have no matching radii (val here)."""
    return (df.split == "val") & (df.intended == "concentric")


def test_intended_relation_holds_in_plain_scenes(scenes: pd.DataFrame) -> None:
    """Every plain pair holds its relation, except concentric pairs of a split whose parts have
    no radii that match (the 3 parts of val here): stacked all the same, the truth says no."""
    assert not _holds_intended(scenes[_unmatched(scenes)]).all()
    plain = scenes[scenes.near_side == ""]
    holds = _holds_intended(plain).groupby([plain.split, plain.intended]).mean()
    log.info("intended relation holds in plain scenes: %s", holds.to_dict())
    assert holds.drop(("val", "concentric")).min() >= 0.99


def test_near_boundary_pairs_straddle_the_rule(scenes: pd.DataFrame) -> None:
    near = scenes[scenes.near_side != ""]
    assert near.near_boundary.all()
    assert set(near.near_side) == {"inside", "outside"}
    assert set(near.intended) == set(NAMES)
    near = near[~_unmatched(near)]
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


def test_a_part_added_changes_only_the_scenes_it_joins(parts: list[ScenePart],
                                                      scenes: pd.DataFrame) -> None:
    """A block added to the library (no axis: no concentric pool) joins a few pairs; every
    other scene is drawn as before, poses and all, so the night's cache keeps its captures."""
    block = scene_part("box-new", "brakes-clutches-couplings", bd.Box(30, 20, 10).wrapped)
    again = generate_scenes([*parts, block], CFG).set_index("scene_id")
    before = scenes.set_index("scene_id")
    assert list(again.index) == list(before.index)
    changed = [i for i in before.index if not again.loc[i].equals(before.loc[i])]
    assert changed and all("box-new" in (again.loc[i, "part_a"], again.loc[i, "part_b"])
                           for i in changed)
    assert len(changed) <= 0.3 * len(before)
    assert not [i for i in changed if again.loc[i, "intended"] == "concentric"]


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


def test_no_interpenetration(scenes: pd.DataFrame, parts: list[ScenePart]) -> None:
    _check_apart(scenes, parts)
    assert (scenes.part_a != scenes.part_b).all()


def test_a_part_is_never_paired_with_itself() -> None:
    """A pool of one part for a relation gives no scene for it (two instances of one part
    would be one part to every later stage), and no scene pairs a part with itself."""
    parts = [scene_part("box", "x", bd.Box(40.0, 30.0, 5.0).wrapped),
             scene_part("cyl", "x", bd.Cylinder(5.0, 30.0).wrapped)]
    cfg = replace(CFG, pairs_per_relation=8, val_fraction=0.0, test_fraction=0.0)
    df = generate_scenes(parts, cfg)
    assert (df.part_a != df.part_b).all()
    assert "concentric" not in set(df.intended)  # only the cylinder has an axis
    assert set(df.intended) >= {r.value for r in Relation if r is not Relation.CONCENTRIC}


def test_a_night_with_too_few_parts_says_so_once(caplog: pytest.LogCaptureFixture) -> None:
    """A night draws its scenes from one pool: the warning names the relations it could not
    pair in one line, and no split."""
    parts = [scene_part("cyl", "x", bd.Cylinder(5.0, 30.0).wrapped)]
    with caplog.at_level("WARNING", logger="cadio.truth.scenes"):
        df = generate_scenes(parts, night_scene_config(seed=0, pairs_per_relation=2))
    assert df.empty
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "split" not in lines[0]
    assert lines[0].startswith("no scene for left, right,") and "of the 1 parts fit" in lines[0]


def test_positives_are_made_the_way_assemblies_make_them(scenes: pd.DataFrame) -> None:
    """Concentric pairs are nested or stacked with faces within the gap; coincident pairs rest
    face to face: every plain one holds (checked above) with its evidence."""
    plain = scenes[(scenes.near_side == "") & ~_unmatched(scenes)]
    conc = plain[plain.intended == "concentric"]
    assert (conc.concentric_gap_mm <= TOL.concentric_gap_mm).all()
    assert (conc.contact_measured).all()
    coin = plain[plain.intended == "coincident"]
    assert (coin.coincident_gap_mm <= 1e-6).all()
    assert not coin.parallel.any()  # coincident pairs are not parallel


def test_near_misses_of_the_face_mates_are_flagged(scenes: pd.DataFrame) -> None:
    near = scenes[(scenes.near_side != "") & scenes.intended.isin(["concentric", "coincident"])
                  & ~_unmatched(scenes)]
    assert len(near) and near.near_boundary.all()
    for relation in ("concentric", "coincident"):
        rows = near[near.intended == relation]
        assert rows[f"{relation}_near"].all()
        assert (rows[relation] == (rows.near_side == "inside")).all()


def _only(parts: list[ScenePart], intended: str, **count: int) -> pd.DataFrame:
    """Scenes of one extra kind alone (``count``: its config field), each pair two different
    parts, labelled by the truth, sharing no volume."""
    cfg = replace(CFG, pairs_per_relation=0, val_fraction=0.0, test_fraction=1.0, **count)
    df = generate_scenes(parts, cfg)
    assert len(df) == sum(count.values()) and (df.intended == intended).all()
    assert df.scene_id.is_unique and (df.part_a != df.part_b).all()
    _check_labels(df, parts, cfg)
    _check_apart(df, parts)
    return df


def _unmoved(parts: list[ScenePart], intended: str, **extra: int) -> None:
    """The other scenes of a config do not move when scenes of ``intended`` are added."""
    more = replace(CFG, pairs_per_relation=6, **extra)
    fewer = replace(more, **{f"{intended}_pairs": 0})
    plain, both = generate_scenes(parts, fewer), generate_scenes(parts, more)
    pd.testing.assert_frame_equal(plain, both[both.intended != intended].reset_index(drop=True))


def test_touching_pairs_meet_without_sharing_volume(parts: list[ScenePart]) -> None:
    """``contact_pairs`` places parts against each other at random orientations: they touch
    (within a tenth of the contact tolerance), share no volume, are labelled by the truth, and
    are seldom face mates, as most touching pairs of an assembly are not."""
    df = _only(parts, CONTACT, contact_pairs=12)
    by_id = {p.part_id: p for p in parts}
    gaps = [exact_gap(by_id[r["part_a"]].model, *scene_poses(r)[:1], by_id[r["part_b"]].model,
                      scene_poses(r)[1]) for _, r in df.iterrows()]
    assert max(gaps) <= 0.1 * TOL.contact_mm, gaps
    mates = df.coincident | df.concentric
    assert mates.mean() <= 0.25, df[mates].scene_id.tolist()
    table = scenes_table(df)
    assert table.intended.tolist() == [CONTACT] and table.scenes.tolist() == [12]
    assert table.holds.iloc[0] == pytest.approx(1.0 - mates.mean(), abs=1e-3)
    _unmoved(parts, CONTACT, contact_pairs=3)


def test_clearance_pairs_are_coaxial_with_their_faces_apart(parts: list[ScenePart]) -> None:
    """``clearance_pairs`` puts two parts on one axis, a shaft in a bore or two ends stacked,
    with 1.5 to 4 mm between them: coaxial without a concentric mate, and clear of its
    near-boundary margin. Without them every coaxial pair of the generator is a mate."""
    df = _only(parts, CLEARANCE, clearance_pairs=16)
    assert not df.concentric.any() and not df.concentric_near.any()
    by_id = {p.part_id: p for p in parts}
    low, high = (f * TOL.concentric_gap_mm for f in CFG.clearance_factors)
    nested = 0
    for _, row in df.iterrows():
        pose_a, pose_b = scene_poses(row)
        gap = exact_gap(by_id[row["part_a"]].model, pose_a, by_id[row["part_b"]].model, pose_b)
        assert low - 1e-6 <= gap <= high + 1e-6, (row["scene_id"], gap)
        spans = [sorted(float((q[:3, :3] @ corner + q[:3, 3])[2]) for corner in
                        (by_id[row[k]].features.bbox_min, by_id[row[k]].features.bbox_max))
                 for k, q in (("part_a", pose_a), ("part_b", pose_b))]
        nested += min(spans[0][1], spans[1][1]) > max(spans[0][0], spans[1][0])
        # pins and rings are cylinders about their own Z axis: the placed axes are one line
        za, zb = pose_a[:3, 2], pose_b[:3, 2]
        assert abs(float(za @ zb)) > np.cos(np.radians(TOL.coaxial_deg)), row["scene_id"]
        offset = pose_b[:3, 3] - pose_a[:3, 3]
        assert np.linalg.norm(offset - (offset @ za) * za) <= TOL.coaxial_mm, row["scene_id"]
    assert 0 < nested < len(df)  # shafts in bores (their Z spans overlap) and stacked ends
    _unmoved(parts, CLEARANCE, contact_pairs=3, clearance_pairs=3)


def test_eligibility(parts: list[ScenePart], scenes: pd.DataFrame) -> None:
    cube = scene_part("cube", "x", bd.Box(20, 20, 20).wrapped)  # no dominant direction
    ball = scene_part("ball", "x", bd.Sphere(10).wrapped)
    assert is_eligible(cube, Relation.LEFT, CFG) and is_eligible(ball, Relation.LEFT, CFG)
    assert not is_eligible(cube, Relation.PARALLEL, CFG)
    assert is_eligible(cube, Relation.COINCIDENT, CFG)
    assert not is_eligible(ball, Relation.COINCIDENT, CFG)
    assert not is_eligible(ball, Relation.CONCENTRIC, CFG)
    conc = scenes[scenes.intended == "concentric"]
    assert not (set(conc.part_a) | set(conc.part_b)) & {p.part_id for p in parts
                                                        if p.part_id.startswith("box")}


def test_write_read_round_trip(scenes: pd.DataFrame, tmp_path: Path) -> None:
    path = tmp_path / "scenes.parquet"
    write_scenes(path, scenes)
    back = read_scenes(path)
    pd.testing.assert_frame_equal(back, scenes)
    assert back.attrs["config"]["tolerances"]["coplanar_mm"] == TOL.coplanar_mm
    assert back.attrs["config"]["seed"] == CFG.seed
    # a kept table is reused only while its stamp is the generator's: the config and the
    # placement rules it was drawn by (a corpus reused scenes drawn by older rules before)
    assert back.attrs["config"] == scenes_stamp(CFG) != scenes_stamp(replace(CFG, seed=1))
    assert len(back.attrs["config"]["generator"]) == 16
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
    parts = [scene_part(p.name, "fasteners", bd.import_step(p).solids()[0].wrapped)
             for p in sorted(FASTENERS.iterdir())]
    cfg = SceneConfig(seed=1, pairs_per_relation=30, near_boundary_fraction=0.2,
                      val_fraction=0.0, test_fraction=0.3)
    df = generate_scenes(parts, cfg)
    assert len(df) > 0
    _check_labels(df, parts, cfg)
    _check_apart(df, parts)
    plain = df[df.near_side == ""]
    fraction = _holds_intended(plain).mean()
    by_relation = _holds_intended(plain).groupby(plain.intended).mean()
    log.info("real fasteners: intended holds in %.4f of %d plain scenes: %s", fraction,
             len(plain), by_relation.to_dict())
    assert fraction >= 0.95 and by_relation.min() >= 0.7
    near = df[df.near_side != ""]
    assert (_holds_intended(near) == (near.near_side == "inside")).all()
