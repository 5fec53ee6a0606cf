"""Scenes: pairs of catalog parts placed so that each of the ten relations holds (the paper).

Following the paper's protocol (III.B), each pair is built for one *intended* relation, the way
assemblies make it (``cadio.truth.placement``): directional pairs put the centre-to-centre
direction within the 15 degree cone of an axis; concentric pairs stack two parts end to end on
one axis or nest a shaft in a bore, their cylinder or cone faces within ``concentric_gap_mm``;
coincident pairs rest a planar face of one part on one of the other; parallel and
perpendicular pairs turn the parts' dominant plane directions vertical (or one horizontal),
apart. Every part also turns about the vertical at random, and gaps are random within a range.
The ten labels of every pair come from the one truth function on the placed parts
(``cadio.truth.labels.label_placed``: face mates for coincident and concentric), never from
the intent, which is recorded separately. A part is never paired with itself. Touching pairs
(``SceneConfig.contact_pairs``: none in a night, drawn by the training corpus) put two parts
against each other at random orientations (``placement.touch``): contact that is seldom a face
mate, as most touching pairs of an assembly are not. Clearance pairs (``clearance_pairs``,
likewise) put two parts on one axis with their faces 1.5 to 4 mm apart: coaxial without a
concentric mate.

Near-boundary pairs sit just inside or just outside a tolerance (the generator's margins), and
any pair whose truth lies within the margins of a tolerance is flagged too.

Parts, not pairs, are split into train/val/test (from a hash of the seed and the part id, so a
part keeps its split when the catalog grows), and pairs only join parts of one split. Each scene
draws from a generator of its own, and a pair of two parts is the two that rank first under the
scene's hash of their ids (``stable_pair``: a uniform draw), so a part added to the library
changes the scenes it ranks first in, not every scene after it: the night's captures of the
others stay in its cache. Concentric and clearance pairs are chosen among the pool's pairs
that fit on one axis, with one generator for all of them: they are drawn again when a part
that could be one joins. The table written here (one row per scene, poses in mm) is what the
capture stage renders.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from OCP.TopoDS import TopoDS_Shape

from cadio.contracts import ScenesSummary
from cadio.records import DIRECTIONAL, Features, FloatArray, Relation
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth import placement
from cadio.truth.labels import PartModel, label_placed, part_model
from cadio.truth.placement import Offers, offers_of, rest_on, touch
from cadio.truth.relations import (
    EVIDENCE_COLUMNS,
    RelationResult,
)
from cadio.truth.scene_config import SceneConfig
from cadio.truth.scene_poses import (
    INSIDE,
    OUTSIDE,
    coaxial,
    directional,
    near_factor,
    parallel_or_perpendicular,
)
from cadio.workspace import Workspace, atomic_write, read_features

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")
COLUMNS = ("scene_id", "split", "part_a", "part_b", "category_a", "category_b", "pose_a",
           "pose_b", "intended", "near_boundary", "near_side",
           *(r.value for r in Relation), *EVIDENCE_COLUMNS)
_METADATA_KEY = b"mateqa.scenes"


@dataclass(frozen=True, eq=False)
class ScenePart:
    """A catalog part offered to the scene generator, described in its own frame (mm)."""

    part_id: str
    category: str
    model: PartModel

    @property
    def features(self) -> Features:
        return self.model.part.features


def scene_part(part_id: str, category: str, shape: TopoDS_Shape,
               tol: Tolerances = DEFAULT_TOLERANCES,
               features: Features | None = None) -> ScenePart:
    """A part for the generator from its solid (and its features where already known)."""
    return ScenePart(part_id, category, part_model(shape, part_id, tol, features))


def assign_splits(part_ids: Sequence[str], seed: int, val_fraction: float,
                  test_fraction: float) -> dict[str, str]:
    """Split of each part: a uniform draw from sha256(seed, part id), stable per part."""
    out = {}
    for pid in part_ids:
        u = int(hashlib.sha256(f"{seed}:{pid}".encode()).hexdigest()[:15], 16) / 16.0**15
        out[pid] = "test" if u < test_fraction else (
            "val" if u < test_fraction + val_fraction else "train")
    return out


def is_eligible(part: ScenePart, relation: Relation, cfg: SceneConfig,
                offers: Offers | None = None) -> bool:
    """Whether a part can take part in a pair built for ``relation``: any part for the
    directional ones; a dominant plane direction carrying ``min_plane_area_fraction`` of the
    area for parallel and perpendicular (the paper's "large flat surfaces"); a rest face for
    coincident and an axial end or cylinder for concentric (``offers``: the part's, where
    known)."""
    f = part.features
    if relation in DIRECTIONAL:
        return True
    if relation in (Relation.PARALLEL, Relation.PERPENDICULAR):
        return dominant_area(f, cfg.tolerances) >= cfg.min_plane_area_fraction * f.area > 0.0
    found = offers_of(part.model) if offers is None else offers
    if relation is Relation.COINCIDENT:
        return bool(found.rests)
    return bool(found.ends or found.bores)


def dominant_area(f: Features, tol: Tolerances) -> float:
    """The planar area carried by the dominant plane direction, mm^2 (0 without one)."""
    if f.dominant_plane is None:
        return 0.0
    cos = math.cos(math.radians(tol.dominant_group_deg))
    return float(sum(g.area for g in f.planes
                     if abs(float(np.dot(g.normal, f.dominant_plane))) >= cos - 1e-9))


def label_pair(a: ScenePart, b: ScenePart, pose_a: FloatArray, pose_b: FloatArray,
               cfg: SceneConfig) -> RelationResult:
    """The relations of a placed pair: the truth (``label_placed``) on parts moved by (4, 4)
    poses (mm)."""
    labels = label_placed([a.model, b.model], [pose_a, pose_b], cfg.view_axis,
                          cfg.tolerances, cfg.margins)
    return labels.relation(0, 1)


def generate_scenes(parts: Sequence[ScenePart], cfg: SceneConfig,
                    splits: Mapping[str, str] | None = None) -> pd.DataFrame:
    """Pairs of parts placed for each relation, with the ten labels from the truth.

    Args:
        parts: catalog parts described in their own frames (mm); ids must be unique.
        cfg: the generator's knobs; a fixed seed gives identical scenes.
        splits: part id -> split where the caller fixes them (a training corpus whose other
            learned stages split the same parts); default drawn from ``cfg`` per part.

    Returns:
        One row per scene: scene_id, split, part_a, part_b, category_a, category_b, pose_a and
        pose_b (16 floats, row-major 4x4 part-to-world, mm), intended, near_boundary, near_side
        ("inside", "outside" or ""), one bool per relation name, then the truth's evidence.
        ``df.attrs["config"]`` holds the config and tolerances.

    Raises:
        ValueError: duplicated part ids or fractions outside [0, 1].
    """
    by_id = {p.part_id: p for p in parts}
    if len(by_id) != len(parts):
        raise ValueError("part ids must be unique")
    if min(cfg.split_fractions().values()) < 0 or not 0 <= cfg.near_boundary_fraction <= 1:
        raise ValueError(f"fractions must lie in [0, 1]: {cfg}")
    drawn = assign_splits(sorted(by_id), cfg.seed, cfg.val_fraction, cfg.test_fraction)
    splits = {pid: (splits or {}).get(pid, drawn[pid]) for pid in by_id}
    offers: dict[str, Offers] = {}
    rows: list[dict[str, Any]] = []
    one_pool = sum(f > 0 for f in cfg.split_fractions().values()) == 1
    for s, split in enumerate(SPLITS):
        members = [by_id[pid] for pid in sorted(by_id) if splits[pid] == split]
        placed, unfit = _relation_scenes(members, offers, split, s, cfg)
        rows += placed
        rows += _contact_scenes(members, offers, split, s, cfg)
        rows += _clearance_scenes(members, offers, split, s, cfg)
        if unfit:
            where = "" if one_pool else f" in split {split}"
            log.warning("no scene for %s: fewer than two of the %d parts%s fit",
                        ", ".join(unfit), len(members), where)
    df = pd.DataFrame(rows, columns=list(COLUMNS))
    df.attrs["config"] = scenes_stamp(cfg)
    return df


def _relation_scenes(members: Sequence[ScenePart], offers: dict[str, Offers], split: str,
                     s: int, cfg: SceneConfig) -> tuple[list[dict[str, Any]], list[str]]:
    """The scenes of each relation in one split (``offers`` filled where the relation needs
    them), and the relations no two parts of the split fit."""
    rows: list[dict[str, Any]] = []
    unfit: list[str] = []
    for r, relation in enumerate(Relation):
        n = _split_count(cfg, split)
        if not n:
            continue
        if relation in (Relation.COINCIDENT, Relation.CONCENTRIC):
            for p in members:
                if p.part_id not in offers:
                    offers[p.part_id] = offers_of(p.model)
        pool = [p for p in members if is_eligible(p, relation, cfg, offers.get(p.part_id))]
        if len(pool) < 2:  # a part beside itself would be one part to later stages
            unfit.append(relation.value)
            continue
        # a concentric pair is chosen among the pool's fitting pairs (``coaxial``), so its
        # scenes share one generator and are drawn again when that pool changes
        shared = np.random.default_rng([cfg.seed, s, r])
        rows += [_scene(pool, offers, relation, split, i, n,
                        shared if relation is Relation.CONCENTRIC else
                        np.random.default_rng([cfg.seed, s, r, i]), cfg) for i in range(n)]
    return rows, unfit


def stable_pair(pool: Sequence[ScenePart], *salt: Any) -> tuple[ScenePart, ScenePart]:
    """Two different parts of the pool: the first and second under a hash of ``salt`` and
    each part id (a uniform draw that a part added to the pool changes only where it ranks
    first or second)."""
    ranked = sorted(pool, key=lambda p: hashlib.sha256(
        json.dumps([*map(str, salt), p.part_id]).encode()).hexdigest())
    return ranked[0], ranked[1]


def scenes_stamp(cfg: SceneConfig) -> dict[str, Any]:
    """What a scene table is drawn with: the config (tuples as lists, as JSON gives them back)
    and a digest of the placement rules' source (this module and ``cadio.truth.placement``).
    A kept table whose stamp differs is stale: ``read_scenes(path).attrs["config"] !=
    scenes_stamp(cfg)``."""
    digest = hashlib.sha256()
    for source in (Path(__file__), Path(placement.__file__)):
        digest.update(source.read_bytes())
    generator = digest.hexdigest()[:16]
    return {**json.loads(json.dumps(asdict(cfg))), "generator": generator}


def scene_poses(row: Any) -> tuple[FloatArray, FloatArray]:
    """The (4, 4) float64 poses (mm) of a scene row (from a frame or ``read_scenes``)."""
    return (np.asarray(row["pose_a"], dtype=np.float64).reshape(4, 4),
            np.asarray(row["pose_b"], dtype=np.float64).reshape(4, 4))


def write_scenes(path: Path, df: pd.DataFrame) -> None:
    """Write the scene table as parquet, atomically; ``df.attrs["config"]`` goes in metadata."""
    table = pa.Table.from_pandas(df, preserve_index=False)
    meta = dict(table.schema.metadata or {})
    meta[_METADATA_KEY] = json.dumps(df.attrs.get("config", {})).encode()
    with atomic_write(Path(path)) as fh:
        pq.write_table(table.replace_schema_metadata(meta), fh)


def read_scenes(path: Path) -> pd.DataFrame:
    """Read a table written by ``write_scenes``; poses come back as lists of 16 floats."""
    table = pq.read_table(path)
    df = table.to_pandas()
    for col in ("pose_a", "pose_b"):
        df[col] = [list(map(float, v)) for v in df[col]]
    raw = (table.schema.metadata or {}).get(_METADATA_KEY)
    df.attrs["config"] = json.loads(raw) if raw else {}
    return df


# ---------------------------------------------------------------- one scene


def _split_count(cfg: SceneConfig, split: str, total: int | None = None) -> int:
    """Pairs per relation (or ``total``) in a split; train takes the remainder so the total
    is exact."""
    total = cfg.pairs_per_relation if total is None else total
    fr = cfg.split_fractions()
    val, test = (round(total * fr[k]) for k in ("val", "test"))
    return {"val": val, "test": test, "train": max(0, total - val - test)}[split]


CONTACT = "contact"  # the intent of the touching pairs (no relation: whatever the truth says)


def _contact_scenes(members: Sequence[ScenePart], offers: dict[str, Offers], split: str,
                    s: int, cfg: SceneConfig) -> list[dict[str, Any]]:
    """The split's ``contact_pairs`` share of touching pairs (``placement.touch``)."""
    n = _split_count(cfg, split, cfg.contact_pairs)
    if not n or len(members) < 2:
        return []
    rows = []
    for i in range(n):
        rng = np.random.default_rng([cfg.seed, s, len(Relation), i])
        a, b = stable_pair(members, cfg.seed, split, CONTACT, i)
        for p in (a, b):
            if p.part_id not in offers:
                offers[p.part_id] = offers_of(p.model)
        pose_a, pose_b = touch(offers[a.part_id], offers[b.part_id], rng)
        rows.append(_placed_row((a, b), (pose_a, pose_b), CONTACT, split, i, False, "", cfg))
    return rows


CLEARANCE = "clearance"  # the intent of coaxial pairs apart (whatever the truth says)


def _clearance_scenes(members: Sequence[ScenePart], offers: dict[str, Offers], split: str,
                      s: int, cfg: SceneConfig) -> list[dict[str, Any]]:
    """The split's ``clearance_pairs`` share of coaxial pairs apart (``clearance_factors``)."""
    n = _split_count(cfg, split, cfg.clearance_pairs)
    if not n:
        return []
    for p in members:
        if p.part_id not in offers:
            offers[p.part_id] = offers_of(p.model)
    pool = [p for p in members
            if is_eligible(p, Relation.CONCENTRIC, cfg, offers[p.part_id])]
    if len(pool) < 2:
        return []
    rng = np.random.default_rng([cfg.seed, s, len(Relation) + 1])  # as concentric scenes'
    low, high = (f * cfg.tolerances.concentric_gap_mm for f in cfg.clearance_factors)
    rows = []
    for i in range(n):
        a, b, pose_a, pose_b = _concentric(pool, offers, "", rng, cfg, (low, high))
        rows.append(_placed_row((a, b), (pose_a, pose_b), CLEARANCE, split, i, False, "", cfg))
    return rows


def _scene(pool: Sequence[ScenePart], offers: Mapping[str, Offers], relation: Relation,
           split: str, i: int, n: int, rng: np.random.Generator,
           cfg: SceneConfig) -> dict[str, Any]:
    """One pair for ``relation``; the first ``near_boundary_fraction`` of them near a boundary."""
    near = i < round(n * cfg.near_boundary_fraction)
    side = (INSIDE if i % 2 == 0 else OUTSIDE) if near else ""
    if relation is Relation.CONCENTRIC:
        a, b, pose_a, pose_b = _concentric(pool, offers, side, rng, cfg)
    else:
        a, b = stable_pair(pool, cfg.seed, split, relation.value, i)  # never a part with itself
        if relation is Relation.COINCIDENT:
            lift = near_factor(side, cfg) * cfg.tolerances.contact_mm
            pose_a, pose_b = rest_on(offers[a.part_id], offers[b.part_id], lift, rng)
        elif relation in DIRECTIONAL:
            pose_a, pose_b = directional(a.features, b.features, relation, side, rng, cfg)
        else:
            pose_a, pose_b = parallel_or_perpendicular(a.features, b.features, relation,
                                                       side, rng, cfg)
    return _placed_row((a, b), (pose_a, pose_b), relation.value, split, i, near, side, cfg)


def _placed_row(parts: tuple[ScenePart, ScenePart], poses: tuple[FloatArray, FloatArray],
                intended: str, split: str, i: int, near: bool, side: str,
                cfg: SceneConfig) -> dict[str, Any]:
    """The table row of a placed pair: centred, labelled by the truth."""
    a, b = parts
    pose_a, pose_b = _centred(a.features, b.features, *poses)
    result = label_pair(a, b, pose_a, pose_b, cfg)
    return {
        "scene_id": f"s{cfg.seed}-{split}-{intended}-{i:05d}", "split": split,
        "part_a": a.part_id, "part_b": b.part_id,
        "category_a": a.category, "category_b": b.category,
        "pose_a": pose_a.ravel().tolist(), "pose_b": pose_b.ravel().tolist(),
        "intended": intended, "near_boundary": near or result.near_boundary(),
        "near_side": side, **result.to_row(),
    }


def _centred(a: Features, b: Features, pose_a: FloatArray,
             pose_b: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Shift both poses so that the midpoint of the placed centroids is the world origin."""
    mid = 0.5 * (pose_a[:3, :3] @ a.centroid + pose_a[:3, 3]
                 + pose_b[:3, :3] @ b.centroid + pose_b[:3, 3])
    pose_a, pose_b = pose_a.copy(), pose_b.copy()
    pose_a[:3, 3] -= mid
    pose_b[:3, 3] -= mid
    return pose_a, pose_b


# ---------------------------------------------------------------- placements


def _concentric(pool: Sequence[ScenePart], offers: Mapping[str, Offers], side: str,
                rng: np.random.Generator, cfg: SceneConfig,
                apart: tuple[float, float] | None = None
                ) -> tuple[ScenePart, ScenePart, FloatArray, FloatArray]:
    """Two parts of the pool on one axis (``scene_poses.coaxial``), in random order."""
    i, j, pose_i, pose_j = coaxial([offers[p.part_id] for p in pool],
                                   [p.features for p in pool], side, rng, cfg, apart)
    return _ordered(pool[i], pool[j], pose_i, pose_j, rng)


def _ordered(p: ScenePart, q: ScenePart, pose_p: FloatArray, pose_q: FloatArray,
             rng: np.random.Generator) -> tuple[ScenePart, ScenePart, FloatArray, FloatArray]:
    """The pair as (a, b) in random order, so that neither role is always below."""
    if rng.random() < 0.5:
        return p, q, pose_p, pose_q
    return q, p, pose_q, pose_p


# ---------------------------------------------------------------- the stage


def build_scenes(catalog: pd.DataFrame, workspace: Path, cfg: SceneConfig,
                 splits: Mapping[str, str] | None = None) -> ScenesSummary:
    """The scenes stage: scenes of the catalog's single parts, written to ``scenes.parquet``
    (``splits``: part id -> split where the caller fixes them, as ``generate_scenes``)."""
    ws = Workspace(Path(workspace))
    parts = read_scene_parts(catalog, ws.root, cfg.tolerances,
                             None if splits is None else set(splits))
    table = generate_scenes(parts, cfg, splits)
    write_scenes(ws.scenes, table)
    return ScenesSummary(path=str(ws.scenes), scenes=len(table), parts=len(parts))


def read_scene_parts(catalog: pd.DataFrame, workspace: Path,
                     tol: Tolerances = DEFAULT_TOLERANCES,
                     only: set[str] | None = None) -> list[ScenePart]:
    """Catalog parts usable in scenes: ok solids of single-part files, each read again from its
    STEP file (the truth measures its faces) with its features from the workspace.

    Solids of assemblies are left out: they are placed in their assembly, not free parts.
    ``only``: part ids to keep (default all).

    Raises:
        StepReadError: a part's file can no longer be read.
    """
    from cadio.cad.step import read_step

    ws = Workspace(Path(workspace))
    rows = catalog[(catalog["status"] == "ok") & (catalog["n_solids"] == 1)]
    out = []
    for r in rows.itertuples():
        pid = str(r.part_id)
        if only is not None and pid not in only:
            continue
        solid = read_step(Path(str(r.source)))[int(r.solid_index)]
        out.append(scene_part(pid, str(r.category), solid.shape, tol,
                              read_features(ws.features(pid))))
    return out
