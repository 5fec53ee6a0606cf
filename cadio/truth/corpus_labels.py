"""The truth of a training corpus's shots: the ten relations of their pairs, view by view.

A shot of the corpus (``models.training.corpus``) is a pair scene or an assembly as placed,
seen from a few cameras. Its pairs are labelled by the one truth function of placed parts
(``cadio.truth.labels.label_placed``: face mates decide coincident and concentric, dominant
plane directions parallel and perpendicular), and the directional relations of each view by
that view's camera (the observer's forward axis on the ground is "behind"), exactly as the
nightly's pairs are. Each pair also carries the CAD's kinematic joint, read from its face
mates as the nightly's ``assembly_joints`` reads it (``cadio.truth.mates.placed_joints``): the
label of the relation networks' joint head. One crash-isolated worker job per shot reads the
parts' solids from their STEP files; a shot that fails is left out with its reason.

Pairs of a shot: the pair of a pair scene; in an assembly, every pair with a face mate, then
the others nearest first, at most ``max_pairs``: the nightly scores every pair of an
assembly, most of them apart, so training sees them as often as they come (with only as many
unmated pairs as mated ones, the networks learned a prior of one mate in two and answered
concentric and coincident for distant pairs of real assemblies).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from cadio.cad.step import read_step
from cadio.records import FloatArray
from cadio.sandbox import Job, Limits, run_isolated
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.joints import NONE
from cadio.truth.labels import label_placed, part_model
from cadio.truth.mates import placed_joints
from cadio.truth.relations import relate
from cadio.workspace import read_features

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LabelPart:
    """One instance of a shot: its STEP file and solid index, features file and pose (mm)."""

    instance: int
    part_id: str
    source: str
    solid_index: int
    features_path: str
    pose_mm: tuple[float, ...]  # 16 floats, row-major (4, 4), part -> shot frame


@dataclass(frozen=True)
class LabelJob:
    """A shot to label: its parts, each view's forward axis (V, 3) and the pair budget."""

    shot: str
    kind: str
    parts: tuple[LabelPart, ...]
    views: tuple[int, ...]
    forward: tuple[tuple[float, float, float], ...]
    max_pairs: int = 60
    tolerances: Tolerances = DEFAULT_TOLERANCES


@dataclass(frozen=True, eq=False)
class ShotLabels:
    """The labelled pairs of a shot.

    pairs: (P, 2) instance ids (a, b). views: (V,) view indices. truth, near: (P, V, 10) bool,
    the relations of (a, b) for each view's observer and whether each sits near its boundary.
    joints: (P,) str, the CAD's kinematic joint of (a, b) (``cadio.truth.joints``), ``"none"``
    when its face mates constrain nothing.
    """

    shot: str
    pairs: npt.NDArray[np.int64]
    views: npt.NDArray[np.int64]
    truth: npt.NDArray[np.bool_]
    near: npt.NDArray[np.bool_]
    joints: npt.NDArray[np.str_]


def label_shot(job: LabelJob) -> ShotLabels:
    """The labelled pairs of one shot (the job of an isolated worker)."""
    files: dict[str, list] = {}  # type: ignore[type-arg]
    models, poses = [], []
    for part in job.parts:
        if part.source not in files:
            files[part.source] = read_step(Path(part.source))
        solid = files[part.source][part.solid_index]
        models.append(part_model(solid.shape, part.part_id, job.tolerances,
                                 read_features(Path(part.features_path))))
        poses.append(np.asarray(part.pose_mm, dtype=np.float64).reshape(4, 4))
    placed = label_placed(models, poses, tol=job.tolerances)
    kinematic = placed_joints(placed, job.tolerances)
    chosen = _pairs(job, placed.face_mates.contact, [p.features.centroid for p in placed.parts])
    truth = np.zeros((len(chosen), len(job.views), 10), dtype=bool)
    near = np.zeros_like(truth)
    for k, (i, j) in enumerate(chosen):
        a, b = placed.parts[i], placed.parts[j]
        contact = placed.face_mates.contact(i, j)
        for v, forward in enumerate(job.forward):
            result = relate(a.features, b.features, forward, job.tolerances, contact,
                            placed.margins)
            truth[k, v], near[k, v] = result.truth, result.near
    ids = np.array([[job.parts[i].instance, job.parts[j].instance] for i, j in chosen],
                   dtype=np.int64).reshape(-1, 2)
    joints = np.array([kinematic.get((min(i, j), max(i, j)), NONE) for i, j in chosen],
                      dtype=np.str_)
    return ShotLabels(job.shot, ids, np.array(job.views, dtype=np.int64), truth, near, joints)


def _pairs(job: LabelJob, contact: Callable[[int, int], object],
           centroids: Sequence[FloatArray]) -> list[tuple[int, int]]:
    """The ordered pairs (indices into the shot's parts) to label."""
    n = len(job.parts)
    if job.kind == "pair" or n == 2:
        return [(0, 1)]
    unordered = [(i, j) for i in range(n) for j in range(i + 1, n)]
    mated = [p for p in unordered if _mated(contact(*p))]
    rest = sorted((p for p in unordered if p not in set(mated)),
                  key=lambda p: float(np.linalg.norm(centroids[p[0]] - centroids[p[1]])))
    return (mated + rest)[:job.max_pairs]


def _mated(contact: object) -> bool:
    return bool(getattr(contact, "coincident", False) or getattr(contact, "concentric", False))


def label_shots(jobs: Sequence[LabelJob], limits: Limits | None = None) -> Iterator[
        tuple[LabelJob, ShotLabels | None, str]]:
    """Each job with its labels, or None and the reason it failed, as workers finish."""
    for outcome in run_isolated(label_shot, [Job(j.shot, j) for j in jobs], limits or Limits()):
        if outcome.result is not None:
            yield outcome.job.payload, outcome.result, ""
        else:
            reason = outcome.error.reason if outcome.error is not None else "no result"
            log.warning("shot %s: %s", outcome.job.key, reason)
            yield outcome.job.payload, None, reason
