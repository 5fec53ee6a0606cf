"""Scenes: pairs of catalog parts placed so that each of the ten relations holds (the paper).

Following the paper's protocol (III.B), each pair is built for one *intended* relation:
directional pairs put the centre-to-centre direction within the 15 degree cone of an axis;
concentric pairs stack two parts with a principal axis on one vertical axis line; parallel,
perpendicular and coincident pairs take parts with large planar faces and turn their principal
plane normals vertical (or one horizontal), coincident ones face to face in contact. Every part
also turns about the vertical axis at random, and gaps are random within a range. The ten labels
of every pair come from ``relations.relate`` on the placed features, never from the intent, which
is recorded separately. Near-boundary pairs sit just inside or just outside a tolerance.

Parts, not pairs, are split into train/val/test (from a hash of the seed and the part id, so a
part keeps its split when the catalog grows), and pairs only join parts of one split. The table
written here (one row per scene, poses in mm) is what the capture stage renders.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from cadio.contracts import ScenesSummary
from cadio.records import DIRECTIONAL, Features, FloatArray, Relation
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.relations import (
    CAD_VIEW_AXIS,
    EVIDENCE_COLUMNS,
    RelationResult,
    direction_axes,
    principal_plane_group,
    relate,
)
from cadio.workspace import Workspace, atomic_write, read_features

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")
COLUMNS = ("scene_id", "split", "part_a", "part_b", "category_a", "category_b", "pose_a",
           "pose_b", "intended", "near_boundary", "near_side",
           *(r.value for r in Relation), *EVIDENCE_COLUMNS)
INSIDE, OUTSIDE = "inside", "outside"
_Z = np.array([0.0, 0.0, 1.0])
_METADATA_KEY = b"mateqa.scenes"


@dataclass(frozen=True)
class ScenePart:
    """A catalog part offered to the scene generator; features in part coordinates (mm)."""

    part_id: str
    category: str
    features: Features


@dataclass(frozen=True)
class SceneConfig:
    """Knobs of the scene generator. Lengths mm, angles degrees."""

    seed: int = 0
    pairs_per_relation: int = 100  # over all splits, shared in proportion to the split fractions
    near_boundary_fraction: float = 0.1  # of each relation's pairs; half inside, half outside
    gap_mm: tuple[float, float] = (5.0, 50.0)  # clearance between the parts' bounding boxes
    val_fraction: float = 0.1
    test_fraction: float = 0.2
    view_axis: tuple[float, float, float] = CAD_VIEW_AXIS
    # "Large flat surfaces" (paper): the principal plane group carries this share of the area.
    min_plane_area_fraction: float = 0.1
    near_directional_deg: float = 1.0  # 14 vs 16 degrees for the 15 degree cone
    near_plane_deg: float = 0.1  # 0.9 vs 1.1 degrees for parallel, 89.1 vs 88.9 perpendicular
    near_inside_factor: float = 0.5  # offsets of 0.05 mm (coplanar, coaxial tolerance 0.1 mm)
    near_outside_factor: float = 2.0  # ... against 0.2 mm
    tolerances: Tolerances = field(default=DEFAULT_TOLERANCES)

    def split_fractions(self) -> dict[str, float]:
        return {"train": 1.0 - self.val_fraction - self.test_fraction,
                "val": self.val_fraction, "test": self.test_fraction}


def assign_splits(part_ids: Sequence[str], seed: int, val_fraction: float,
                  test_fraction: float) -> dict[str, str]:
    """Split of each part: a uniform draw from sha256(seed, part id), stable per part."""
    out = {}
    for pid in part_ids:
        u = int(hashlib.sha256(f"{seed}:{pid}".encode()).hexdigest()[:15], 16) / 16.0**15
        out[pid] = "test" if u < test_fraction else (
            "val" if u < test_fraction + val_fraction else "train")
    return out


def is_eligible(part: ScenePart, relation: Relation, cfg: SceneConfig) -> bool:
    """Whether a part can take part in a pair built for ``relation`` (paper's selection)."""
    f = part.features
    if relation in DIRECTIONAL:
        return True
    if relation is Relation.CONCENTRIC:
        return f.principal_axis is not None
    group = principal_plane_group(f)
    return group is not None and bool(group.offsets) and \
        group.area >= cfg.min_plane_area_fraction * f.area


def label_pair(a: Features, b: Features, pose_a: FloatArray, pose_b: FloatArray,
               cfg: SceneConfig) -> RelationResult:
    """The relations of a placed pair: ``relate`` on features moved by (4, 4) poses (mm)."""
    return relate(a.transformed(pose_a), b.transformed(pose_b), cfg.view_axis, cfg.tolerances)


def generate_scenes(parts: Sequence[ScenePart], cfg: SceneConfig,
                    splits: Mapping[str, str] | None = None) -> pd.DataFrame:
    """Pairs of parts placed for each relation, with the ten labels from ``relate``.

    Args:
        parts: catalog parts with features in part coordinates (mm); ids must be unique.
        cfg: the generator's knobs; a fixed seed gives identical scenes.
        splits: part id -> split where the caller fixes them (a training corpus whose other
            learned stages split the same parts); default drawn from ``cfg`` per part.

    Returns:
        One row per scene: scene_id, split, part_a, part_b, category_a, category_b, pose_a and
        pose_b (16 floats, row-major 4x4 part-to-world, mm), intended, near_boundary, near_side
        ("inside", "outside" or ""), one bool per relation name, then ``relate``'s evidence.
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
    rows: list[dict[str, Any]] = []
    for s, split in enumerate(SPLITS):
        members = [by_id[pid] for pid in sorted(by_id) if splits[pid] == split]
        for r, relation in enumerate(Relation):
            pool = [p for p in members if is_eligible(p, relation, cfg)]
            n = _split_count(cfg, split)
            if n and len(pool) < 2:  # a part beside itself would be one part to later stages
                log.warning("fewer than two parts in split %s fit %s: skipped", split,
                            relation.value)
            if not (n and len(pool) >= 2):
                continue
            rng = np.random.default_rng([cfg.seed, s, r])
            rows += [_scene(pool, relation, split, i, n, rng, cfg) for i in range(n)]
    df = pd.DataFrame(rows, columns=list(COLUMNS))
    df.attrs["config"] = json.loads(json.dumps(asdict(cfg)))  # tuples become lists
    return df


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


def _split_count(cfg: SceneConfig, split: str) -> int:
    """Pairs per relation in a split; train takes the remainder so the total is exact."""
    fr = cfg.split_fractions()
    val, test = (round(cfg.pairs_per_relation * fr[k]) for k in ("val", "test"))
    return {"val": val, "test": test, "train": max(0, cfg.pairs_per_relation - val - test)}[split]


def _scene(pool: Sequence[ScenePart], relation: Relation, split: str, i: int, n: int,
           rng: np.random.Generator, cfg: SceneConfig) -> dict[str, Any]:
    """One pair for ``relation``; the first ``near_boundary_fraction`` of them near a boundary."""
    near = i < round(n * cfg.near_boundary_fraction)
    side = (INSIDE if i % 2 == 0 else OUTSIDE) if near else ""
    ia = int(rng.integers(len(pool)))
    ib = (ia + 1 + int(rng.integers(len(pool) - 1))) % len(pool)  # never a part with itself
    a, b = pool[ia], pool[ib]
    pose_a, pose_b = _centred(a.features, b.features,
                              *_place(a.features, b.features, relation, side, rng, cfg))
    result = label_pair(a.features, b.features, pose_a, pose_b, cfg)
    return {
        "scene_id": f"s{cfg.seed}-{split}-{relation.value}-{i:05d}", "split": split,
        "part_a": a.part_id, "part_b": b.part_id,
        "category_a": a.category, "category_b": b.category,
        "pose_a": pose_a.ravel().tolist(), "pose_b": pose_b.ravel().tolist(),
        "intended": relation.value, "near_boundary": near, "near_side": side,
        **result.to_row(),
    }


def _place(a: Features, b: Features, relation: Relation, side: str, rng: np.random.Generator,
           cfg: SceneConfig) -> tuple[FloatArray, FloatArray]:
    if relation in DIRECTIONAL:
        return _directional(a, b, relation, side, rng, cfg)
    if relation is Relation.CONCENTRIC:
        return _concentric(a, b, side, rng, cfg)
    if relation is Relation.COINCIDENT:
        return _coincident(a, b, side, rng, cfg)
    return _parallel_or_perpendicular(a, b, relation, side, rng, cfg)


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


def _directional(a: Features, b: Features, relation: Relation, side: str,
                 rng: np.random.Generator, cfg: SceneConfig) -> tuple[FloatArray, FloatArray]:
    """a's centroid off b's along a direction at a chosen angle from the relation's axis."""
    ra, rb = _spin(rng), _spin(rng)
    a0, b0 = a.transformed(_pose(ra)), b.transformed(_pose(rb))
    axis = direction_axes(cfg.view_axis)[DIRECTIONAL.index(relation)]
    cone, margin = cfg.tolerances.direction_cone_deg, cfg.near_directional_deg
    if side:
        theta = cone - margin if side == INSIDE else cone + margin
    else:  # uniform over the spherical cap of half-angle cone - margin
        theta = math.degrees(math.acos(rng.uniform(math.cos(math.radians(cone - margin)), 1)))
    u = _tilt(axis, theta, rng)
    t = _separation(_rel_box(a0), _rel_box(b0), u) + rng.uniform(*cfg.gap_mm)
    return _pose(ra, t * u - a0.centroid), _pose(rb, -b0.centroid)


def _concentric(a: Features, b: Features, side: str, rng: np.random.Generator,
                cfg: SceneConfig) -> tuple[FloatArray, FloatArray]:
    """Principal axes on the world Z line, one part stacked above the other."""
    assert a.principal_axis is not None and b.principal_axis is not None
    ra = _spin(rng) @ _align(a.principal_axis.direction, _Z * rng.choice([-1.0, 1.0]))
    rb = _spin(rng) @ _align(b.principal_axis.direction, _Z * rng.choice([-1.0, 1.0]))
    a0, b0 = a.transformed(_pose(ra)), b.transformed(_pose(rb))
    assert a0.principal_axis is not None and b0.principal_axis is not None
    ta = -a0.principal_axis.point * np.array([1.0, 1.0, 0.0])
    tb = -b0.principal_axis.point * np.array([1.0, 1.0, 0.0])
    if side:
        factor = cfg.near_inside_factor if side == INSIDE else cfg.near_outside_factor
        ta = ta + _tilt(_Z, 90.0, rng) * factor * cfg.tolerances.coaxial_mm
    ta[2], tb[2] = _stack(a0, b0, rng, cfg)
    return _pose(ra, ta), _pose(rb, tb)


def _parallel_or_perpendicular(a: Features, b: Features, relation: Relation, side: str,
                               rng: np.random.Generator,
                               cfg: SceneConfig) -> tuple[FloatArray, FloatArray]:
    """a's principal normal vertical; b's vertical (parallel) or horizontal (perpendicular)."""
    assert a.principal_plane is not None and b.principal_plane is not None
    near = cfg.tolerances.parallel_deg + (
        -cfg.near_plane_deg if side == INSIDE else cfg.near_plane_deg)
    ra = _spin(rng) @ _align(a.principal_plane, _Z * rng.choice([-1.0, 1.0]))
    if relation is Relation.PARALLEL:
        tilt = _rot(_tilt(_Z, 90.0, rng), near) if side else np.eye(3)
        rb = _spin(rng) @ tilt @ _align(b.principal_plane, _Z * rng.choice([-1.0, 1.0]))
    else:  # normal to +X, raised by the near-boundary elevation, then spun about Z
        raise_ = _rot(np.array([0.0, 1.0, 0.0]), -near) if side else np.eye(3)
        rb = _spin(rng) @ raise_ @ _align(b.principal_plane, np.array([1.0, 0.0, 0.0]))
    a0, b0 = a.transformed(_pose(ra)), b.transformed(_pose(rb))
    if relation is Relation.PARALLEL:  # stacked: disjoint heights, so no face is coplanar
        za, zb = _stack(a0, b0, rng, cfg)
        shift = _lateral(a0, b0, rng)
        return _pose(ra, np.array([0.0, 0.0, za]) - a0.centroid * [1, 1, 0] + shift), \
            _pose(rb, np.array([0.0, 0.0, zb]) - b0.centroid * [1, 1, 0])
    u = _tilt(_Z, math.degrees(math.acos(rng.uniform(-1.0, 1.0))), rng)
    t = _separation(_rel_box(a0), _rel_box(b0), u) + rng.uniform(*cfg.gap_mm)
    return _pose(ra, t * u - a0.centroid), _pose(rb, -b0.centroid)


def _coincident(a: Features, b: Features, side: str, rng: np.random.Generator,
                cfg: SceneConfig) -> tuple[FloatArray, FloatArray]:
    """b's lowest down-facing principal face laid on a's highest up-facing one."""
    ra, top = _extreme_face(a, +1, rng)
    rb, bottom = _extreme_face(b, -1, rng)
    a0, b0 = a.transformed(_pose(ra)), b.transformed(_pose(rb))
    factor = {"": 0.0, INSIDE: cfg.near_inside_factor, OUTSIDE: cfg.near_outside_factor}[side]
    tb = np.zeros(3)
    tb[2] = top - bottom + factor * cfg.tolerances.coplanar_mm
    # Faces at the box extremes (B-rep boxes carry ~1e-7 mm of slack): stack, in contact.
    if b0.bbox_min[2] + tb[2] >= a0.bbox_max[2] - 0.01 * cfg.tolerances.coplanar_mm:
        tb[:2] = rng.uniform(a0.bbox_min[:2], a0.bbox_max[:2]) - b0.centroid[:2]
    else:  # the boxes would interpenetrate: put the parts side by side on the common plane
        w = _tilt(_Z, 90.0, rng)
        box_b = (b0.bbox_min + tb, b0.bbox_max + tb)
        move = _separation(box_b, (a0.bbox_min, a0.bbox_max), w) + rng.uniform(*cfg.gap_mm)
        tb[:2] += move * w[:2]
    return _pose(ra), _pose(rb, tb)


def _extreme_face(f: Features, facing: int, rng: np.random.Generator) -> tuple[FloatArray, float]:
    """A rotation turning the principal normal vertical so that a principal face faces up
    (facing=+1) or down (-1) at the part's top (bottom), and that face's height (mm)."""
    assert f.principal_plane is not None
    best: list[tuple[float, FloatArray, float]] = []
    for sign in (1.0, -1.0):
        rot = _spin(rng) @ _align(f.principal_plane, sign * _Z)
        moved = f.transformed(_pose(rot))
        group = principal_plane_group(moved)
        assert group is not None
        heights = [o for o, w in zip(group.offsets, group.outward, strict=True) if w == facing]
        if heights:
            h = max(heights) if facing > 0 else min(heights)
            edge = moved.bbox_max[2] if facing > 0 else moved.bbox_min[2]
            best.append((abs(edge - h) + 1e-9 * rng.random(), rot, h))
    _, rot, height = min(best, key=lambda x: x[0])
    return rot, height


# ---------------------------------------------------------------- geometry helpers


def _pose(rot: FloatArray, t: Any = (0.0, 0.0, 0.0)) -> FloatArray:
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = t
    return m


def _rot(axis: FloatArray, deg: float) -> FloatArray:
    """Rotation matrix (3, 3) about a unit axis by ``deg`` degrees (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]],
                 dtype=np.float64)
    th = math.radians(deg)
    rot: FloatArray = np.eye(3) + math.sin(th) * k + (1 - math.cos(th)) * (k @ k)
    return rot


def _spin(rng: np.random.Generator) -> FloatArray:
    return _rot(_Z, rng.uniform(0.0, 360.0))


def _align(u: FloatArray, w: FloatArray) -> FloatArray:
    """The smallest rotation (3, 3) turning unit vector u onto unit vector w."""
    u = np.asarray(u, dtype=np.float64) / np.linalg.norm(u)
    axis = np.cross(u, w)
    s, c = float(np.linalg.norm(axis)), float(np.dot(u, w))
    if s < 1e-12:  # parallel or opposite: any perpendicular axis serves for the half turn
        other = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        perp = np.cross(u, other)
        return np.eye(3) if c > 0 else _rot(perp / np.linalg.norm(perp), 180.0)
    return _rot(axis / s, math.degrees(math.atan2(s, c)))


def _tilt(axis: FloatArray, deg: float, rng: np.random.Generator) -> FloatArray:
    """A unit vector at ``deg`` degrees from ``axis``, at a random azimuth about it."""
    other = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    side = np.cross(axis, other)
    side = _rot(axis, rng.uniform(0.0, 360.0)) @ (side / np.linalg.norm(side))
    th = math.radians(deg)
    tilted: FloatArray = math.cos(th) * axis + math.sin(th) * side
    return tilted


def _rel_box(f: Features) -> tuple[FloatArray, FloatArray]:
    """The bounding box relative to the centroid, mm."""
    return f.bbox_min - f.centroid, f.bbox_max - f.centroid


def _separation(box_a: tuple[FloatArray, FloatArray], box_b: tuple[FloatArray, FloatArray],
                u: FloatArray) -> float:
    """Smallest t >= 0 (mm) such that box_a moved by t*u no longer overlaps box_b."""
    ts: list[float] = []
    for k in range(3):
        if u[k] > 1e-9:
            ts.append(float((box_b[1][k] - box_a[0][k]) / u[k]))
        elif u[k] < -1e-9:
            ts.append(float((box_b[0][k] - box_a[1][k]) / u[k]))
    return max(0.0, min(ts))


def _stack(a0: Features, b0: Features, rng: np.random.Generator,
           cfg: SceneConfig) -> tuple[float, float]:
    """Z shifts (mm) putting one box above the other (random order) with a random gap."""
    gap = rng.uniform(*cfg.gap_mm)
    if rng.random() < 0.5:  # a on top
        return float(b0.bbox_max[2] - a0.bbox_min[2] + gap), 0.0
    return 0.0, float(a0.bbox_max[2] - b0.bbox_min[2] + gap)


def _lateral(a0: Features, b0: Features, rng: np.random.Generator) -> FloatArray:
    """A random horizontal shift (mm) within half the parts' combined footprint."""
    half = 0.25 * ((a0.bbox_max - a0.bbox_min) + (b0.bbox_max - b0.bbox_min))
    return np.array([rng.uniform(-half[0], half[0]), rng.uniform(-half[1], half[1]), 0.0])


def build_scenes(catalog: pd.DataFrame, workspace: Path, cfg: SceneConfig,
                 splits: Mapping[str, str] | None = None) -> ScenesSummary:
    """The scenes stage: scenes of the catalog's single parts, written to ``scenes.parquet``
    (``splits``: part id -> split where the caller fixes them, as ``generate_scenes``)."""
    ws = Workspace(Path(workspace))
    parts = read_scene_parts(catalog, ws.root)
    if splits is not None:  # a training corpus: only the parts its other stages split
        parts = [p for p in parts if p.part_id in splits]
    table = generate_scenes(parts, cfg, splits)
    write_scenes(ws.scenes, table)
    return ScenesSummary(path=str(ws.scenes), scenes=len(table), parts=len(parts))


def read_scene_parts(catalog: pd.DataFrame, workspace: Path) -> list[ScenePart]:
    """Catalog parts usable in scenes: ok solids of single-part files, with their features.

    Solids of assemblies are left out: they are placed in their assembly, not free parts.
    """
    ws = Workspace(Path(workspace))
    rows = catalog[(catalog["status"] == "ok") & (catalog["n_solids"] == 1)]
    return [ScenePart(str(r.part_id), str(r.category), read_features(ws.features(str(r.part_id))))
            for r in rows.itertuples()]
