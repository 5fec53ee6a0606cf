"""The relation networks' dataset: the labelled pairs of a corpus's shots, view by view.

The corpus (``models.training.corpus``) holds, for every shot (a pair scene or an assembly as
placed) and every view, each instance's observed points and camera, and each instance's CAD
surface samples as placed; its truth (``cadio.truth.corpus_labels``) labels the shot's pairs
for each view's observer. ``build_relation_dataset`` turns them into one ``<split>.npz`` per
split: for each input (``truth``: CAD samples; ``partial``: the observed points of that view;
``completed``: the completion network's shape from that single view, the surface of its solid)
the two parts' points in the observer's frame (N, 2, k, 3) float32, their pair evidence
(``cadio.evidence.pair_features``, raw, (N, F)), for ``truth`` the centroids of the two parts'
solids in the observer's frame (N, 2, 3) (the other inputs' centres are their points' means:
``models.geometric.network_evidence``), the labels (N, 10), whether the pair sits near
a tolerance in that view, the CAD's kinematic joint of the pair (``"none"`` without one), and
which shot, view, parts and category each row is. Points are kept
in float32: a tenth of a millimetre in a metre-sized scene needs it (float16 rounds it away).

The pair evidence of ``truth`` and ``completed`` is measured on denser clouds than the k
points the networks read (``evidence_points``, as the nightly does: ``PairConfig``): up to that
many CAD surface samples, and surface voxels of the completion. At 600 points per part the
mating faces of an assembly's parts hold a handful of points, metres apart in a large part
(``bench/studies/evidence_density.py``). ``partial`` keeps the corpus's stored observed points.

A pair whose parts are not both of the shot's split is left out (a training assembly holding a
test part does not leak it), as the corpus leaves out their completion examples.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from cadio.capture.examples import read_example
from cadio.capture.observe import observer_rotation
from cadio.capture.pointcloud import sample_points
from cadio.evidence.cad_samples import placed_cad_samples
from cadio.evidence.pair_features import pair_features_many
from cadio.evidence.pairs import PairConfig, evidence_cloud, pair_category
from cadio.truth.corpus_labels import ShotLabels
from cadio.workspace import atomic_write, features_of_mesh, read_mesh
from models.geometric import network_evidence, tests_for, with_observed
from models.relation_inputs import INPUTS, trained
from models.relations import JOINTS
from models.relations_train import RelationData, nearest_of_pairs
from models.train import Model, predict
from models.training.corpus import Shot
from reports.metrics import surface_points

log = logging.getLogger(__name__)

META = ("scene", "view", "part_a", "part_b", "category", "kind", "near_boundary",
        "scale_m_per_mm", "joint")
THRESHOLD = 0.5  # a voxel of the completion is solid above this probability


@dataclass(frozen=True)
class RelationSplit:
    """One split of the dataset: inputs (name -> (N, 2, k, 3) float32 observer frame), raw
    pair evidence (name -> (N, F) float32), labels (N, 10) bool and the rows' provenance
    (``META`` columns)."""

    inputs: dict[str, npt.NDArray[np.float32]]
    features: dict[str, npt.NDArray[np.float32]]
    near: dict[str, npt.NDArray[np.float32]]
    labels: npt.NDArray[np.bool_]
    meta: pd.DataFrame
    # input -> (N, 2, 3) observer-frame centres of the parts where the input knows its solids
    centres: dict[str, npt.NDArray[np.float64]] = field(default_factory=dict)

    def centres_of(self, name: str) -> npt.NDArray[np.float64] | None:
        """(N, 2, 3) the parts' centres of one input, or None: the means of its points."""
        return self.centres.get(name)

    def data(self, name: str, rows: npt.NDArray[np.bool_] | None = None) -> RelationData:
        """One input's pairs as its networks read them, of ``rows`` (default all): the points
        (the observed ones for an input that reads them, ``RelationInput.observed_by``) and
        ``evidence``."""
        keep = np.ones(len(self.labels), dtype=bool) if rows is None else rows
        mm = 1.0 / self.meta["scale_m_per_mm"].to_numpy(dtype=np.float64)
        points = INPUTS.get(name).observed_by or name
        return RelationData(self.inputs[points][keep], self.labels[keep], mm[keep],
                            self.evidence(name)[keep], self.near[points][keep],
                            self.joints()[keep])

    def network_evidence(self, name: str) -> npt.NDArray[np.float32]:
        """(N, len(``EVIDENCE``)) one input's ``models.geometric.network_evidence``."""
        centres = self.centres_of(name)
        return network_evidence(self.features[name], self.inputs[name], centres,
                                tests_for(name))

    def evidence(self, name: str) -> npt.NDArray[np.float32]:
        """What a network of one input reads: its ``network_evidence``, with the observed
        points' after it where it reads them (``RelationInput.observed_by``, ``with_observed``)."""
        own = self.network_evidence(name)
        observed = INPUTS.get(name).observed_by
        return own if observed is None else with_observed(own, self.network_evidence(observed))

    def joints(self) -> npt.NDArray[np.int64]:
        """(N,) each row's CAD joint as an index into ``JOINTS`` (-1: a joint the head does
        not name, such as fastened)."""
        index = {name: k for k, name in enumerate(JOINTS)}
        return np.array([index.get(str(j), -1) for j in self.meta["joint"]], dtype=np.int64)


@dataclass
class _Row:
    shot: Shot
    view: int
    a: int
    b: int
    labels: npt.NDArray[np.bool_]
    near: bool
    joint: str
    scale: float
    w2c: npt.NDArray[np.float64]
    points: dict[str, npt.NDArray[np.float32]]
    # input -> the two parts' denser clouds of the pair evidence (world metres); absent: points
    evidence: dict[str, tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]]
    centres: npt.NDArray[np.float64]  # (2, 3) the centroids of the parts' solids, world metres


def build_relation_dataset(corpus_dir: Path, shots: Sequence[Shot],
                           labels: Mapping[str, ShotLabels], index: pd.DataFrame,
                           completion: Model | None, out_dir: Path, cfg: PairConfig,
                           progress: Callable[[str], None] | None = None) -> dict[str, int]:
    """Write ``<split>.npz`` of every split of the shots' labelled pair views; rows per split.

    Args:
        corpus_dir: the corpus (its ``views/<shot>.npz`` and examples).
        shots: the corpus's shots; those without labels are skipped.
        labels: shot id -> its labelled pairs (``corpus_labels.label_shots``).
        index: the corpus's example index (the single views the completion network sees).
        completion: the completion network (``gan_lstm``, observed protocol); without it a pair
            view has no ``completed`` input and is left out.
        cfg: the nightly's pair inputs (``PairConfig``: points per part, the fewest observed
            points a part must show in a view, points of the ``truth`` and ``completed`` pair
            evidence).
    """
    singles = _single_views(index)
    by_split: dict[str, list[_Row]] = {}
    for shot in shots:
        if shot.shot_id not in labels:
            continue
        try:
            rows = _shot_rows(corpus_dir, shot, labels[shot.shot_id], singles, completion,
                              cfg)
        except (OSError, ValueError, KeyError) as exc:
            log.warning("shot %s: %s", shot.shot_id, exc)
            continue
        if rows:
            by_split.setdefault(shot.split, []).extend(rows)
        if progress is not None:
            progress(shot.shot_id)
    out_dir.mkdir(parents=True, exist_ok=True)
    for split, rows in by_split.items():
        write_split(out_dir / f"{split}.npz", rows)
    return {s: len(r) for s, r in sorted(by_split.items())}


def _single_views(index: pd.DataFrame) -> dict[tuple[str, int, int], str]:
    """(shot, instance, view) -> the file of its single-view observed example."""
    ok = index[(index["status"] == "ok") & (index["protocol"] == "observed")
               & (index["n_views"] == 1)]
    return {(str(r.shot), int(r.instance), int(r.views[0])): str(r.file)
            for r in ok.itertuples()}


def _shot_rows(corpus_dir: Path, shot: Shot, truth: ShotLabels,
               singles: Mapping[tuple[str, int, int], str], completion: Model | None,
               cfg: PairConfig) -> list[_Row]:
    parts = {p.instance: p for p in shot.parts}
    with np.load(corpus_dir / "views" / f"{shot.shot_id}.npz") as z:
        seen = {(int(i), int(v)): k for k, (i, v) in enumerate(zip(z["instance"], z["view"],
                                                                    strict=True))}
        partial, observed, w2c = z["partial"], z["observed"], z["world_to_camera"]
        cad = dict(zip(z["truth_instance"].tolist(), z["truth"], strict=True))
        scale = float(z["scale_m_per_mm"])
    completed: dict[tuple[int, int], tuple[npt.NDArray[np.float32],
                                           npt.NDArray[np.float32]]] = {}
    dense_cad: dict[int, tuple[npt.NDArray[np.float32], npt.NDArray[np.float64]]] = {}
    rows = []
    for (a, b), per_view, near, joint in zip(truth.pairs.tolist(), truth.truth, truth.near,
                                             truth.joints.tolist(), strict=True):
        if parts[a].split != shot.split or parts[b].split != shot.split:
            continue
        for v, view in enumerate(truth.views.tolist()):
            ka, kb = seen.get((a, view)), seen.get((b, view))
            if ka is None or kb is None or min(observed[ka], observed[kb]) < cfg.min_observed:
                continue
            points = {"truth": np.stack([cad[a], cad[b]]),
                      "partial": np.stack([partial[ka], partial[kb]])}
            done_a, done_b = (_completed(corpus_dir, shot.shot_id, k, view, singles,
                                         completion, completed, cfg)
                              for k in (a, b))
            if done_a is None or done_b is None:
                continue
            points["completed"] = np.stack([done_a[0], done_b[0]])
            for k in (a, b):
                if k not in dense_cad:
                    dense_cad[k] = placed_samples(shot, k, cfg.evidence_points, scale)
            evidence = {"truth": (dense_cad[a][0], dense_cad[b][0]),
                        "completed": (done_a[1], done_b[1])}
            rows.append(_Row(shot, view, a, b, per_view[v], bool(near[v].any()), joint, scale,
                             w2c[ka], {k: p.astype(np.float32) for k, p in points.items()},
                             evidence, np.stack([dense_cad[a][1], dense_cad[b][1]])))
    return rows


def placed_samples(shot: Shot, instance: int, k: int, scale: float
                   ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float64]]:
    """(k, 6): k CAD surface samples of one instance placed as in the shot (world metres),
    seeded by its part as the corpus's own samples are, with the exact normals of their faces
    (``placed_cad_samples``; the features beside the mesh in its workspace); and (3,) the
    centroid of its solid there (world metres)."""
    part = next(p for p in shot.parts if p.instance == instance)
    mesh = Path(part.mesh_path)
    features, pose = features_of_mesh(mesh), part.pose()
    centre = (pose[:3, :3] @ features.centroid + pose[:3, 3]) * scale
    return (placed_cad_samples(read_mesh(mesh), features, part.part_id, pose, k, scale),
            np.asarray(centre, dtype=np.float64))


def _completed(corpus_dir: Path, shot: str, instance: int, view: int,
               singles: Mapping[tuple[str, int, int], str], model: Model | None,
               cache: dict[tuple[int, int], tuple[npt.NDArray[np.float32],
                                                  npt.NDArray[np.float32]]],
               cfg: PairConfig
               ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]] | None:
    """The completion of one instance from one view: ``cfg.n_points`` of its solid's surface
    voxels' centres (world metres) and up to ``cfg.evidence_points`` of them for the pair
    evidence;
    the observed points when the solid is empty."""
    if (instance, view) in cache:
        return cache[(instance, view)]
    file = singles.get((shot, instance, view))
    if model is None or file is None:
        return None
    example = read_example(corpus_dir / file)
    solid = predict(model, [example.inputs], batch_size=1)[0] > THRESHOLD
    n = solid.shape[-1]
    pts = surface_points(solid, example.grid.voxel_m(n), example.grid.grid_to_world(n)) \
        if solid.any() else example.points
    out = (np.asarray(sample_points(np.asarray(pts), cfg.n_points, method="random"),
                      np.float32),
           np.asarray(evidence_cloud(np.asarray(pts), cfg.evidence_points), np.float32))
    cache[(instance, view)] = out
    return out


def write_split(path: Path, rows: Sequence[_Row]) -> None:
    """One split's arrays: per input the observer-frame points, their raw pair evidence (of
    the rows' evidence clouds where they have them) and each point's distance to the other
    part (mm)."""
    arrays: dict[str, Any] = {}
    mm = np.array([1.0 / r.scale for r in rows])
    keys = [((r.shot.shot_id, r.a, r.view), (r.shot.shot_id, r.b, r.view)) for r in rows]
    for name in trained():
        pts = np.stack([r.points[name] @ observer_rotation(r.w2c) for r in rows]
                       ).astype(np.float32)
        arrays[f"points_{name}"] = pts
        clouds = [r.evidence.get(name, tuple(r.points[name])) for r in rows]
        # CAD samples do not change with the view: each instance's cloud is analysed once
        cloud_keys = [((name, ka[0], ka[1]), (name, kb[0], kb[1])) if INPUTS.get(name).exact
                      else ((name, *ka), (name, *kb)) for ka, kb in keys]
        arrays[f"features_{name}"] = pair_features_many(clouds, mm, cloud_keys)
        arrays[f"near_{name}"] = nearest_of_pairs(pts, mm)
    arrays["centres_truth"] = np.stack([r.centres @ observer_rotation(r.w2c) for r in rows])
    arrays["labels"] = np.stack([r.labels for r in rows])
    parts = [{p.instance: p for p in r.shot.parts} for r in rows]
    meta = {
        "scene": [r.shot.shot_id for r in rows], "view": [r.view for r in rows],
        "part_a": [p[r.a].part_id for p, r in zip(parts, rows, strict=True)],
        "part_b": [p[r.b].part_id for p, r in zip(parts, rows, strict=True)],
        "category": [pair_category(p[r.a].category, p[r.b].category)
                     for p, r in zip(parts, rows, strict=True)],
        "kind": [r.shot.kind for r in rows], "near_boundary": [r.near for r in rows],
        "scale_m_per_mm": [r.scale for r in rows], "joint": [r.joint for r in rows]}
    for col in META:
        arrays[col] = np.array(meta[col])
    with atomic_write(path) as fh:
        np.savez(fh, **arrays)


def read_split(path: Path) -> RelationSplit:
    """A split written by ``write_split``."""
    with np.load(path) as z:
        inputs = {n: z[f"points_{n}"].astype(np.float32) for n in trained()}
        features = {n: z[f"features_{n}"].astype(np.float32) for n in trained()}
        near = {n: z[f"near_{n}"].astype(np.float32) for n in trained()}
        meta = pd.DataFrame({col: z[col] for col in META})
        if "centres_truth" not in z:
            raise ValueError(f"{path}: a relation dataset from before the parts' centres: "
                             "rebuild it (mateqa train relations)")
        centres = {"truth": z["centres_truth"].astype(np.float64)}
        return RelationSplit(inputs, features, near, z["labels"].astype(bool), meta, centres)
