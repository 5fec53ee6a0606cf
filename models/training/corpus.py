"""The training corpus of both learned stages: what the nightly's cameras see, as examples.

The nightly sees parts beside and behind others: in pair scenes and inside assemblies as
placed, each scene scaled to the same 0.3 m in front of the same cameras. A corpus of parts
each rendered alone, unoccluded, taught the networks a world the nightly never shows (small
parts of an assembly gave about one point per input voxel; occluded ones a grid that cut them).
So the corpus renders *shots* of three kinds, through the nightly's own renderer and camera
circle, and cuts every instance of every shot into the same inputs the nightly builds:

- ``alone``: one part, posed (``examples.part_pose``), as the nightly captures a part that no
  scene or assembly shows;
- ``pair``: a row of the scene table (``cadio.truth.scenes``): two parts placed for a relation;
- ``assembly``: every solid of a multi-part file, as placed in the file.

Each shot is rendered from ``views`` cameras of the 125-view circle (starting at a seeded
azimuth, so the corpus sees all sides) and gives, per instance seen well enough:

- completion examples (``examples.observed_example`` + ``with_truth``): each view alone and the
  sequences of ``lengths`` views, in the observed protocol (and the oracle-box one for single
  views where asked), written one ``.npz`` each;
- per view, the instance's observed points (``n_points``, world metres) and the camera, and its
  CAD surface samples placed as in the shot (``views.npz`` of the shot): the relation stage's
  ``partial`` and ``truth`` inputs. Labels are not fixed here: the ground truth labels the
  pairs from the poses kept in the shot table.

Splits are by part and by group (an assembly file, a pair scene's parts, a part alone): see
``corpus_splits``. An instance whose part has another split than its shot gives no example
(a training assembly that holds a test part does not leak that part's views into training).
One crash-isolated worker job per shot (``cadio.sandbox``): a shot that fails is an index row
with its reason and the others go on.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cadio.camera.noise import NoiseConfig
from cadio.camera.render import CaptureConfig, PlacedPart, render_views
from cadio.capture.examples import (
    OBSERVED,
    ORACLE,
    ExampleConfig,
    PartView,
    observed_example,
    oracle_example,
    part_pose,
    part_views,
    support_plane,
    view_sets,
    with_truth,
    write_example,
)
from cadio.capture.pointcloud import sample_points
from cadio.evidence.cad_samples import placed_surface_samples
from cadio.records import FloatArray
from cadio.sandbox import Job, Limits, run_isolated
from cadio.workspace import atomic_path, atomic_write, read_mesh

log = logging.getLogger(__name__)

KINDS = ("alone", "pair", "assembly")
SPLIT_ORDER = ("train", "val", "test")  # a shape in several groups takes the most held out
INDEX = "index.parquet"
SHOTS = "shots.parquet"
INDEX_COLUMNS = ("file", "shot", "kind", "group", "part_id", "category", "split", "instance",
                 "protocol", "n_views", "views", "view_deg", "coverage", "observed",
                 "status", "error")


@dataclass(frozen=True)
class CorpusConfig:
    """What each shot contributes. The defaults give 4 views a shot: 4 single-view examples and
    a sequence of 2 views per instance seen, in the observed protocol, and the single views of
    parts alone in the oracle-box protocol too."""

    example: ExampleConfig = field(default_factory=ExampleConfig)
    views: int = 4  # cameras per shot, spread over the circle from a seeded start
    # Sequences of views beside the single views (the headline is one view; the LSTM needs
    # some sequences to learn to merge them).
    lengths: tuple[int, ...] = (2,)
    protocols: tuple[str, ...] = (OBSERVED, ORACLE)
    # Shot kinds whose single views are also cut in the oracle-box protocol (a labelled
    # comparison with the paper's setting: a part alone is the paper's own setting).
    oracle_kinds: tuple[str, ...] = ("alone",)
    n_points: int = 600  # relation inputs per instance and view (the grounding MLP's 600)
    noise: bool = False  # the nightly's default captures are noise-free
    seed: int = 0

    def capture(self) -> CaptureConfig:
        return CaptureConfig(noise=NoiseConfig() if self.noise else None)

    def view_indices(self, shot_id: str) -> list[int]:
        """``views`` indices of the 125-view circle, evenly spread from a start drawn from the
        shot id (so shots of one part see it from different sides)."""
        total = self.capture().n_views
        start = int(hashlib.sha256(f"{self.seed}:{shot_id}".encode()).hexdigest()[:8], 16)
        return sorted({(start + round(i * total / self.views)) % total
                       for i in range(self.views)})


@dataclass(frozen=True)
class ShotPart:
    """One instance of a shot: the catalog part, its mesh file, its pose in the shot (mm)."""

    instance: int
    part_id: str
    category: str
    split: str
    mesh_path: str
    pose_mm: tuple[float, ...]  # 16 floats, row-major (4, 4), part -> shot frame, mm

    def pose(self) -> FloatArray:
        return np.asarray(self.pose_mm, dtype=np.float64).reshape(4, 4)


@dataclass(frozen=True)
class Shot:
    """One thing the corpus renders: a part alone, a pair scene or an assembly as placed."""

    shot_id: str
    kind: str
    group: str  # what the split is drawn for: the part, the scene's parts, the assembly file
    split: str
    parts: tuple[ShotPart, ...]

    def to_row(self) -> dict[str, Any]:
        return {"shot": self.shot_id, "kind": self.kind, "group": self.group,
                "split": self.split, "parts": json.dumps([asdict(p) for p in self.parts])}


@dataclass(frozen=True)
class ShotJob:
    """One shot for a corpus worker."""

    shot: Shot
    out_dir: str
    cfg: CorpusConfig


@dataclass(frozen=True)
class IndexRow:
    """One example file of the corpus (or a shot that gave none, with the reason)."""

    file: str
    shot: str
    kind: str
    group: str
    part_id: str
    category: str
    split: str
    instance: int = 0
    protocol: str = ""
    n_views: int = 0
    views: tuple[int, ...] = ()
    view_deg: float = float("nan")
    coverage: float = float("nan")
    observed: int = 0  # observed points of the instance in the example's first view
    status: str = "ok"
    error: str = ""


def _pose_tuple(pose: FloatArray) -> tuple[float, ...]:
    return tuple(float(v) for v in np.asarray(pose, dtype=np.float64).ravel())


def alone_shots(parts: pd.DataFrame, splits: Mapping[str, str],
                mesh_of: Callable[[str], Path]) -> list[Shot]:
    """One shot per part (catalog rows with part_id and category), posed by ``part_pose``."""
    out = []
    for row in parts.itertuples():
        pid = str(row.part_id)
        mesh_path = mesh_of(pid)
        pose = part_pose(pid, read_mesh(mesh_path))
        split = splits.get(pid, "test")
        part = ShotPart(1, pid, str(row.category), split, str(mesh_path), _pose_tuple(pose))
        out.append(Shot(f"alone-{pid}", "alone", pid, split, (part,)))
    return out


def pair_shots(scenes: pd.DataFrame, splits: Mapping[str, str],
               mesh_of: Callable[[str], Path]) -> list[Shot]:
    """One shot per row of a scene table (its poses, mm). The shot's id holds a digest of its
    parts and poses: a scene drawn anew under the same scene id is a new shot, rendered and
    labelled anew (by id alone, a corpus kept the renders of the old placement)."""
    out = []
    for scene in scenes.to_dict("records"):
        parts = []
        for i, role in enumerate(("a", "b")):
            pid = str(scene[f"part_{role}"])
            pose = np.asarray(scene[f"pose_{role}"], dtype=np.float64).reshape(4, 4)
            parts.append(ShotPart(i + 1, pid, str(scene[f"category_{role}"]),
                                  splits.get(pid, "test"), str(mesh_of(pid)), _pose_tuple(pose)))
        sid = str(scene["scene_id"])
        placed = ";".join(f"{p.part_id}:" + ",".join(f"{v:.6f}" for v in p.pose_mm)
                          for p in parts)
        digest = hashlib.sha256(placed.encode()).hexdigest()[:8]
        out.append(Shot(f"pair-{sid}-{digest}", "pair", sid, str(scene["split"]), tuple(parts)))
    return out


def assembly_shots(catalog: pd.DataFrame, splits: Mapping[str, str],
                   group_splits: Mapping[str, str], mesh_of: Callable[[str], Path],
                   max_parts: int = 40) -> list[Shot]:
    """One shot per multi-part file of the catalog: its ok solids as placed in the file (the
    meshes are in the file's frame). Files of more than ``max_parts`` solids are left out: at
    0.3 m their parts are a few pixels each."""
    ok = catalog[catalog["status"] == "ok"]
    out = []
    for source, rows in ok.groupby("source", sort=True):
        if not 2 <= len(rows) <= max_parts:
            continue
        rows = rows.sort_values("solid_index")
        parts = tuple(ShotPart(i + 1, str(r.part_id), str(r.category),
                               splits.get(str(r.part_id), "test"), str(mesh_of(str(r.part_id))),
                               _pose_tuple(np.eye(4)))
                      for i, r in enumerate(rows.itertuples()))
        group = str(source)
        name = Path(group).stem
        digest = hashlib.sha256(group.encode()).hexdigest()[:8]
        out.append(Shot(f"assembly-{name}-{digest}", "assembly", group,
                        group_splits.get(group, "test"), parts))
    return out


def shot_job(job: ShotJob) -> list[IndexRow]:
    """Render a shot and write its examples and relation inputs (an isolated worker's job)."""
    shot, cfg, out = job.shot, job.cfg, Path(job.out_dir)
    meshes = {p.instance: read_mesh(Path(p.mesh_path)) for p in shot.parts}
    placed = [PlacedPart(instance_id=p.instance, mesh=meshes[p.instance], pose=p.pose(),
                         part_id=p.part_id) for p in shot.parts]
    frames = list(render_views(placed, cfg.capture(), cfg.view_indices(shot.shot_id)))
    if not frames:
        raise ValueError("no view rendered")
    scale = float(frames[0].meta["scale_m_per_mm"])
    labels = [f.instance if f.instance is not None else np.zeros_like(f.depth, dtype=np.int32)
              for f in frames]
    rows: list[IndexRow] = []
    seen: dict[int, list[PartView]] = {}
    supports = [support_plane(f, lab) for f, lab in zip(frames, labels, strict=True)]
    for part in shot.parts:
        views = part_views(frames, labels, part.instance, supports)
        if not views:
            continue
        seen[part.instance] = views
        if part.split != shot.split:
            continue  # a part of another split: its views stay out of this shot's examples
        to_world = np.diag([scale, scale, scale, 1.0]) @ part.pose()
        rows += _instance_examples(shot, part, views, meshes[part.instance], to_world, out, cfg)
    _write_views(out / "views" / f"{shot.shot_id}.npz", shot, seen, meshes, scale, cfg)
    if not rows:
        rows.append(IndexRow("", shot.shot_id, shot.kind, shot.group, "", "", shot.split,
                             status="empty", error="no instance of the shot's split was seen"))
    return rows


def _instance_examples(shot: Shot, part: ShotPart, views: list[PartView], mesh: Any,
                       to_world: FloatArray, out: Path, cfg: CorpusConfig) -> list[IndexRow]:
    rows = []
    for chosen in view_sets(len(views), len(views), cfg.lengths):
        seq = [views[i] for i in chosen]
        for protocol in cfg.protocols:
            if protocol == ORACLE and (len(seq) > 1 or shot.kind not in cfg.oracle_kinds):
                continue  # the oracle-box comparison is made on single views
            example = (observed_example(seq, cfg.example) if protocol == OBSERVED
                       else oracle_example(seq, mesh, to_world, cfg.example))
            example = with_truth(example, mesh, to_world, cfg.example)
            tag = "-".join(map(str, example.views))
            name = f"{shot.shot_id}-{part.instance}-{protocol[:3]}-{tag}.npz"
            meta = {"part_id": part.part_id, "category": part.category, "split": part.split,
                    "shot": shot.shot_id, "kind": shot.kind, "instance": part.instance}
            write_example(out / "examples" / protocol / name, example, meta)
            rows.append(IndexRow(
                file=f"examples/{protocol}/{name}", shot=shot.shot_id, kind=shot.kind,
                group=shot.group, part_id=part.part_id, category=part.category,
                split=part.split, instance=part.instance, protocol=protocol,
                n_views=len(seq), views=example.views, view_deg=example.azimuths[0],
                coverage=example.coverage, observed=len(seq[0].points)))
    return rows


def _write_views(path: Path, shot: Shot, seen: Mapping[int, list[PartView]],
                 meshes: Mapping[int, Any], scale: float, cfg: CorpusConfig) -> None:
    """The relation inputs of a shot: per (instance, view) seen, ``n_points`` observed points
    and the camera; per instance, ``n_points`` CAD surface samples placed as in the shot (world
    metres, float32). Arrays: ``instance`` (R,), ``view`` (R,), ``observed`` (R,) counts,
    ``partial`` (R, k, 3), ``world_to_camera`` (R, 4, 4); ``truth_instance`` (I,), ``truth``
    (I, k, 3); ``scale_m_per_mm``."""
    inst, view, observed, partial, w2c = [], [], [], [], []
    for i, views in sorted(seen.items()):
        for v in views:
            inst.append(i)
            view.append(v.view)
            observed.append(len(v.points))
            partial.append(sample_points(v.points, cfg.n_points))
            w2c.append(v.evidence.world_to_camera)
    truth_ids, truth = [], []
    for part in shot.parts:
        truth_ids.append(part.instance)
        truth.append(placed_surface_samples(meshes[part.instance], part.part_id, part.pose(),
                                            cfg.n_points, scale))
    k = cfg.n_points
    with atomic_write(path) as fh:
        np.savez_compressed(
            fh, instance=np.array(inst, dtype=np.int64), view=np.array(view, dtype=np.int64),
            observed=np.array(observed, dtype=np.int64),
            partial=np.array(partial, dtype=np.float32).reshape(-1, k, 3),
            world_to_camera=np.array(w2c, dtype=np.float64).reshape(-1, 4, 4),
            truth_instance=np.array(truth_ids, dtype=np.int64),
            truth=np.array(truth, dtype=np.float32).reshape(-1, k, 3),
            scale_m_per_mm=np.float64(scale))


def build_corpus(shots: Sequence[Shot], out_dir: Path, cfg: CorpusConfig,
                 limits: Limits | None = None,
                 on_shot: Callable[[str], None] | None = None) -> pd.DataFrame:
    """Render every shot not yet in ``out_dir``'s index, write examples and views, and return
    the merged index (also written, with the shot table, after every 50 shots, so a stopped
    build resumes where it was).

    Raises:
        ValueError: ``out_dir`` holds a corpus of another configuration.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    _check_stamp(out_dir, cfg)
    old = read_index(out_dir / INDEX) if (out_dir / INDEX).exists() else None
    done = set() if old is None else set(old["shot"])
    todo = [s for s in shots if s.shot_id not in done]
    rows: list[IndexRow] = []
    jobs = [Job(s.shot_id, ShotJob(s, str(out_dir), cfg)) for s in todo]
    by_id = {s.shot_id: s for s in todo}
    for n, outcome in enumerate(run_isolated(shot_job, jobs, limits or Limits()), 1):
        shot = by_id[outcome.job.key]
        if outcome.result is not None:
            rows.extend(outcome.result)
        else:
            reason = outcome.error.reason if outcome.error is not None else "no result"
            log.warning("shot %s: %s", shot.shot_id, reason)
            rows.append(IndexRow("", shot.shot_id, shot.kind, shot.group, "", "", shot.split,
                                 status="failed", error=reason))
        if on_shot is not None:
            on_shot(shot.shot_id)
        if n % 50 == 0:
            _save(out_dir, old, rows, shots)
    return _save(out_dir, old, rows, shots)


def _save(out_dir: Path, old: pd.DataFrame | None, rows: Sequence[IndexRow],
          shots: Sequence[Shot]) -> pd.DataFrame:
    """The index and shot table of ``shots``: what was rendered before for a shot no longer
    planned (a scene drawn anew, a part gone from the catalog) leaves both, so training never
    reads it."""
    planned = {s.shot_id for s in shots}
    new = index_frame(rows)
    if old is not None:
        old = old[old["shot"].isin(planned)]
    merged = new if old is None else pd.concat([old, new], ignore_index=True)
    with atomic_path(out_dir / INDEX) as tmp:
        merged.to_parquet(tmp, index=False)
    table = pd.DataFrame([s.to_row() for s in shots]).drop_duplicates("shot")
    with atomic_path(out_dir / SHOTS) as tmp:
        table.to_parquet(tmp, index=False)
    return merged


def _check_stamp(out_dir: Path, cfg: CorpusConfig) -> None:
    stamp = {"n_in": cfg.example.n_in, "n_out": cfg.example.n_out, "views": cfg.views,
             "n_points": cfg.n_points, "noise": cfg.noise, "seed": cfg.seed}
    path = out_dir / "corpus.json"
    if path.exists() and json.loads(path.read_text()) != stamp:
        raise ValueError(f"{out_dir} holds a corpus made with {json.loads(path.read_text())}, "
                         f"not {stamp}: build this one in another folder")
    path.write_text(json.dumps(stamp))


def index_frame(rows: Sequence[IndexRow]) -> pd.DataFrame:
    frame = pd.DataFrame([asdict(r) for r in rows], columns=list(INDEX_COLUMNS))
    frame["views"] = [list(v) for v in frame["views"]]
    return frame


def read_index(path: Path) -> pd.DataFrame:
    return pd.read_parquet(path)


def read_shots(path: Path) -> list[Shot]:
    """The shot table written beside the index."""
    out = []
    for row in pd.read_parquet(path).to_dict("records"):
        parts = tuple(ShotPart(**{**p, "pose_mm": tuple(p["pose_mm"])})
                      for p in json.loads(row["parts"]))
        out.append(Shot(str(row["shot"]), str(row["kind"]), str(row["group"]),
                        str(row["split"]), parts))
    return out


def corpus_splits(groups: Mapping[str, Sequence[str]], shape_of: Mapping[str, str],
                  seed: int = 0,
                  fractions: Callable[[str], tuple[float, float]] = lambda g: (0.1, 0.2)
                  ) -> tuple[dict[str, str], dict[str, str]]:
    """Splits by group and by part.

    Args:
        groups: group (a file) -> the part ids it holds.
        shape_of: part id -> shape key (parts of one geometry in several files share it).
        fractions: group -> (val, test) fractions of its draw; (0, 1) holds a group out (the
            nightly's own sample library).

    Returns:
        (group -> split, part id -> split). A group's split is a uniform draw from
        sha256(seed, group); a part's is the most held-out split among the groups holding its
        shape, so no test shape is trained on through another file.
    """
    group_split = {}
    for g in sorted(groups):
        val, test = fractions(g)
        u = int(hashlib.sha256(f"{seed}:{g}".encode()).hexdigest()[:15], 16) / 16.0**15
        group_split[g] = "test" if u < test else ("val" if u < test + val else "train")
    shape_split: dict[str, str] = {}
    for g, pids in groups.items():
        for pid in pids:
            key = shape_of.get(pid, pid)
            old = shape_split.get(key, "train")
            shape_split[key] = max(old, group_split[g], key=SPLIT_ORDER.index)
    part_split = {pid: shape_split[shape_of.get(pid, pid)] for pids in groups.values()
                  for pid in pids}
    return group_split, part_split


def shape_keys(catalog: pd.DataFrame) -> dict[str, str]:
    """Part id -> a key of its geometry: volume, face count and sorted extents (an assembly's
    bolt and the same bolt as its own file share it, so they share a split)."""
    ok = catalog[catalog["status"] == "ok"]
    out = {}
    for r in ok.itertuples():
        extent = tuple(sorted(np.round(np.subtract(r.bbox_max, r.bbox_min), 3)))
        out[str(r.part_id)] = f"{r.volume:.0f}|{r.n_faces}|{extent}"
    return out


@dataclass(frozen=True)
class CorpusPlan:
    """The shots of a corpus and the splits they were drawn with."""

    shots: list[Shot]
    group_split: dict[str, str]
    part_split: dict[str, str]


def plan_corpus(catalog: pd.DataFrame, mesh_of: Callable[[str], Path], scenes: pd.DataFrame,
                fractions: Callable[[str], tuple[float, float]], seed: int = 0,
                max_assembly_parts: int = 40) -> CorpusPlan:
    """Every shot of a corpus: each distinct part alone, each scene row, each multi-part file.

    Args:
        catalog: the training workspace's catalog.
        scenes: a scene table of its single parts (``cadio.truth.scenes``), drawn with the
            part splits of ``plan_splits`` (pairs join parts of one split).
        fractions: group (source file) -> (val, test) fractions, as ``corpus_splits``.
    """
    group_split, part_split = plan_splits(catalog, fractions, seed)
    ok = catalog[catalog["status"] == "ok"]
    keys = shape_keys(catalog)
    single = ok[ok["n_solids"] == 1].assign(_key=lambda f: f["part_id"].astype(str).map(keys))
    distinct = single.sort_values("part_id").drop_duplicates("_key")
    # Assemblies first: a build stopped early still holds the scenes the nightly finds hardest.
    shots = [*assembly_shots(catalog, part_split, group_split, mesh_of, max_assembly_parts),
             *alone_shots(distinct, part_split, mesh_of),
             *pair_shots(scenes, part_split, mesh_of)]
    return CorpusPlan(shots, group_split, part_split)


def plan_splits(catalog: pd.DataFrame, fractions: Callable[[str], tuple[float, float]],
                seed: int = 0) -> tuple[dict[str, str], dict[str, str]]:
    """``corpus_splits`` of a catalog's ok parts, grouped by source file."""
    ok = catalog[catalog["status"] == "ok"]
    groups = {str(src): [str(p) for p in rows["part_id"]]
              for src, rows in ok.groupby("source", sort=True)}
    return corpus_splits(groups, shape_keys(catalog), seed, fractions)
