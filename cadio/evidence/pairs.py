"""Pairs of parts seen by one camera: the relation stage's inputs and their truth.

A capture (a scene of two parts, or a whole assembly) shows its parts in several views. Each
view of each pair is one ``PairView``: the two parts' points in every relation input, and the
ten relations of the pair *as that camera's observer sees them*. The directional relations follow
the observer (DESIGN.md: the camera's forward axis on the ground is "behind"), so the same pair
seen from the other side swaps left and right; the symmetric ones do not change.

The inputs are the relation inputs' own (``models.relation_inputs``, a module each): each
gives an ``InputBuilder`` that makes its clouds from what a view of a pair offers
(``ViewSources``: the two parts placed as in the capture with their CAD samples, their
observed points in the view), (2, k, 3) float32 world metres, with the denser clouds its
pair evidence is measured on and the parts' centres where it knows them.

The truth labels come from ``cadio.truth.relations.relate`` on the B-rep features of the parts
placed in the CAD frame, with the camera's view axis, and the pair's face mates as the truth
measured them (the scene's ``labels.contact``, or the assembly's mates table): one definition
for scenes and assemblies. The networks see only ``observer_points`` (the points turned into
the observer's frame), never the poses or the features.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from cadio.capture.observe import observer_rotation
from cadio.capture.pointcloud import sample_points
from cadio.errors import CaptureError
from cadio.evidence.cad_samples import placed_cad_samples, placed_surface_samples
from cadio.recordings.mcap_io import read_scene_meta
from cadio.records import Features, FloatArray
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.relations import (
    NO_CONTACT,
    BoundaryMargins,
    PairContact,
    contacts_of_mates,
    relate,
)
from cadio.workspace import Workspace, read_features, read_mesh

Cloud = npt.NDArray[np.float32]


@dataclass(frozen=True)
class PairConfig:
    """Knobs of the relation stage's inputs."""

    n_points: int = 600  # per part (the paper's grounding MLP reads 600)
    # Points per part of the pair evidence of ``truth`` (CAD samples) and ``completed`` (the
    # completion's surface voxels): at 600 a mate's faces hold a few points, a large part's
    # several millimetres apart, while the mates' tolerances are 0.1-1 mm. The observed points
    # stay the capture's ``n_points`` (the training corpus stores no more).
    evidence_points: int = 3000
    # A part showing fewer observed points in a view gives no pair view there (the camera barely
    # saw it; the capture's inputs already drop views under ``examples.MIN_POINTS``).
    min_observed: int = 30
    max_pairs: int = 300  # per capture: an assembly of n parts has n(n - 1)/2 pairs
    margins: BoundaryMargins = field(default_factory=BoundaryMargins)
    tolerances: Tolerances = DEFAULT_TOLERANCES


DEFAULT_PAIRS = PairConfig()


@dataclass(frozen=True, eq=False)
class PairView:
    """One ordered pair of parts in one view.

    labels: (10,) bool in ``Relation`` order, for this view's observer. near: (10,) bool, each
    relation's answer within the margins of a tolerance (near_boundary: any of them). points:
    input name -> (2, k, 3) float32 world metres (part a, part b). world_to_camera: (4, 4) the
    view's camera. evidence: input name -> the two parts' denser clouds (world metres, any
    sizes) its pair evidence is measured on (``PairConfig.evidence_points``); an input without
    them is measured on its points. ``truth``'s are (k, 6): each CAD sample with the exact
    unit normal of its face (``cadio.evidence.cad_samples``). centres: input name -> (2, 3)
    world metres, the centroids of the two parts' solids where the input knows them
    (``truth``: the CAD's); the other inputs' centres are their points' means. slack: input
    name -> millimetres within which its poses place the two parts (a registration's: the
    two poses' uncertainty, ``posed_pair_views``); the evidence's lengths are read within it
    (``models.geometric.within_pose``). An input without one is read as measured. turn_slack:
    likewise, degrees, within which its poses turn the two parts against each other; the
    angle of their dominant directions is read within it.
    """

    scene: str
    view: int
    part_a: str
    part_b: str
    category: str
    labels: npt.NDArray[np.bool_]
    near_boundary: bool
    world_to_camera: FloatArray
    scale_m_per_mm: float
    points: dict[str, Cloud]
    near: npt.NDArray[np.bool_] = field(default_factory=lambda: np.zeros(10, dtype=bool))
    evidence: dict[str, tuple[Cloud, Cloud]] = field(default_factory=dict)
    centres: dict[str, FloatArray] = field(default_factory=dict)
    slack: dict[str, float] = field(default_factory=dict)
    turn_slack: dict[str, float] = field(default_factory=dict)

    def observer_centres(self, name: str) -> FloatArray:
        """(2, 3) float64: the two parts' centres in the observer frame (``observer_points``),
        the solids' centroids where the input knows them, else the points' means."""
        if name in self.centres:
            turned: FloatArray = np.asarray(
                self.centres[name] @ observer_rotation(self.world_to_camera), dtype=np.float64)
            return turned
        means: FloatArray = np.asarray(self.observer_points(name), dtype=np.float64).mean(axis=1)
        return means

    def evidence_clouds(self, name: str) -> tuple[Cloud, Cloud]:
        """The two clouds the pair evidence of input ``name`` is measured on (world metres)."""
        if name in self.evidence:
            return self.evidence[name]
        return self.points[name][0], self.points[name][1]

    def observer_points(self, name: str) -> Cloud:
        """(2, k, 3) float32: the input's points in the observer frame (right, behind, up),
        metres, about the same origin as the world (all a camera and gravity tell)."""
        rot = observer_rotation(self.world_to_camera)
        return np.asarray(self.points[name] @ rot, dtype=np.float32)

    @property
    def view_axis(self) -> FloatArray:
        """(3,) the camera's forward direction in the world."""
        return np.asarray(self.world_to_camera[2, :3], dtype=np.float64)


@dataclass(frozen=True)
class CapturedPart:
    """A part's observed points in every view that saw it (``points.npz``).

    views: (V,) view indices. points: (V, k, 3) float32 world metres. world_to_camera: (V, 4, 4).
    observed: (V,) observed points before sampling.
    """

    part_id: str
    views: npt.NDArray[np.int64]
    points: Cloud
    world_to_camera: FloatArray
    observed: npt.NDArray[np.int64]


def read_part_points(path: Path, part_id: str) -> CapturedPart:
    """A part's ``points.npz``.

    Raises:
        CaptureError: the file is missing or lacks the per-view arrays.
    """
    try:
        with np.load(path) as z:
            return CapturedPart(part_id, z["view"].astype(np.int64),
                                z["points"].astype(np.float32),
                                z["world_to_camera"].astype(np.float64),
                                z["observed"].astype(np.int64))
    except (OSError, KeyError, ValueError) as exc:
        raise CaptureError(path, f"no per-view observed points: {exc}") from exc


def pair_category(a: str, b: str) -> str:
    """The category of a pair: the parts' common category, or both joined by "+"."""
    return a if a == b else "+".join(sorted((a, b)))


def capture_pairs(capture: Path, ws: Workspace, categories: Mapping[str, str],
                  cfg: PairConfig, builders: Mapping[str, InputBuilder]) -> list[PairView]:
    """Every view of every labelled pair of a capture.

    Parts are told apart by their instance in the capture, not their part id: a scene may show
    one part twice, and each instance has its own pose, points and completion.

    Args:
        capture: the MCAP file; its ``/scene`` meta names the parts, their poses and the pairs
            (``labels.pair`` of a scene, ``labels.pairs`` of an assembly, by part id).
        ws: the workspace holding the parts' features, meshes and the capture's inputs.
        categories: part id -> category.
        builders: input name -> the input's clouds of a view of a pair (an input whose
            builder gives none for a view is absent from that view).

    Raises:
        CaptureError: the capture has no scene description, or its pairs no face-mate truth.
    """
    meta = read_scene_meta(capture)
    if not meta or not meta.get("parts"):
        raise CaptureError(capture, "no scene description: its parts are unknown")
    pairs = _instance_pairs(meta)[:cfg.max_pairs]
    contacts = _contacts(capture, meta, ws) if pairs else {}
    placed = {int(p["instance_id"]): p for p in meta["parts"]}
    needed = sorted({k for pair in pairs for k in pair})
    folders = {k: ws.inputs(capture.stem, k) / "points.npz" for k in needed}
    seen = {k: read_part_points(folders[k], str(placed[k]["part_id"]))
            for k in needed if folders[k].exists()}
    scale = float(meta["scale_m_per_mm"])
    parts = {k: PosedPart(str(placed[k]["part_id"]), placed[k], ws, scale, cfg.n_points,
                        cfg.evidence_points) for k in seen}
    out = []
    for a, b in pairs:
        if a in parts and b in parts:
            pa, pb = parts[a].part_id, parts[b].part_id
            pair = _Pair(capture.stem, (a, b), parts[a], parts[b], seen[a], seen[b],
                         pair_category(categories.get(pa, "?"), categories.get(pb, "?")),
                         contacts.get((pa, pb), NO_CONTACT), scale)
            out += _pair_views(pair, cfg, builders)
    return out


def _contacts(capture: Path, meta: dict[str, Any], ws: Workspace
              ) -> dict[tuple[str, str], PairContact]:
    """(part a, part b) -> the face mates' answer: a scene's ``labels.contact``, or the
    assembly's mates table (part-level rows and the answers near a boundary).

    Raises:
        CaptureError: neither is there.
    """
    labels = meta.get("labels") or {}
    if "pair" in labels and "contact" in labels:
        a, b = (str(p) for p in labels["pair"])
        contact = PairContact.from_dict(labels["contact"])
        return {(a, b): contact, (b, a): contact}
    if "assembly" in labels and ws.mates(str(labels["assembly"])).is_file():
        table = pd.read_parquet(ws.mates(str(labels["assembly"])),
                                columns=["part_a", "part_b", "level", "relation"])
        return contacts_of_mates(table.to_dict("records"),
                                 table.attrs.get("near_boundary", []))
    raise CaptureError(capture, "its pairs carry no face-mate truth (a scene without "
                                "labels.contact, or an assembly without its mates table)")


def _instance_pairs(meta: dict[str, Any]) -> list[tuple[int, int]]:
    """The labelled pairs as pairs of instance ids: a part id stands for its instances in order,
    and a pair naming one part twice is its first two instances."""
    instances: dict[str, list[int]] = {}
    for p in meta["parts"]:
        instances.setdefault(str(p["part_id"]), []).append(int(p["instance_id"]))
    out = []
    for a, b in _labelled_pairs(meta):
        first, second = instances.get(a, []), instances.get(b, [])
        if a == b:
            second = second[1:]
        if first and second:
            out.append((first[0], second[0]))
    return out


def _labelled_pairs(meta: dict[str, Any]) -> list[tuple[str, str]]:
    labels = meta.get("labels") or {}
    if "pairs" in labels:
        return [(str(a), str(b)) for a, b in labels["pairs"]]
    if "pair" in labels:
        a, b = labels["pair"]
        return [(str(a), str(b))]
    return []


class PosedPart:
    """A part instance as the capture placed it: its features placed (mm), ``truth``: k
    samples of its CAD surface and ``dense``: the pair evidence's samples with their faces'
    exact normals, (m, 6), and ``centre``: its solid's centroid, all world metres."""

    def __init__(self, part_id: str, meta: dict[str, Any], ws: Workspace, scale: float,
                 k: int, dense: int) -> None:
        pose = np.asarray(meta["pose_mm"], dtype=np.float64)
        self.part_id = part_id
        own = read_features(ws.features(part_id))
        self.features: Features = own.transformed(pose)
        mesh = read_mesh(ws.mesh(part_id))
        self.truth = np.asarray(placed_surface_samples(mesh, part_id, pose, k, scale),
                                dtype=np.float32)
        self.dense = placed_cad_samples(mesh, own, part_id, pose, dense, scale)
        self.centre = np.asarray(self.features.centroid * scale, dtype=np.float64)


@dataclass(frozen=True)
class _Pair:
    """A labelled pair of a capture: its instances, placed parts, observed points and truth."""

    scene: str
    instances: tuple[int, int]
    a: PosedPart
    b: PosedPart
    seen_a: CapturedPart
    seen_b: CapturedPart
    category: str
    contact: PairContact
    scale: float


@dataclass(frozen=True)
class ViewSources:
    """What one view of a pair offers the relation inputs.

    instances: the two parts' instance ids in the capture. placed: the two parts as placed,
    with their CAD samples (``PosedPart``). observed: (2, k, 3) float32 world metres, their
    observed points in this view. view: the view's index.
    """

    capture: str
    view: int
    instances: tuple[int, int]
    placed: tuple[PosedPart, PosedPart]
    observed: Cloud
    cfg: PairConfig


@dataclass(frozen=True)
class InputClouds:
    """One input's clouds of a view of a pair: points (2, k, 3) float32 world metres; the
    denser clouds its evidence is measured on (None: its points); the parts' centres (2, 3)
    world metres where the input knows the solids (None: the points' means)."""

    points: Cloud
    evidence: tuple[Cloud, Cloud] | None = None
    centres: FloatArray | None = None


InputBuilder = Callable[[ViewSources], InputClouds | None]


def _pair_views(pair: _Pair, cfg: PairConfig, builders: Mapping[str, InputBuilder]
                ) -> list[PairView]:
    """The views of one pair, each with every input its builder gives there."""
    index_b = {int(v): i for i, v in enumerate(pair.seen_b.views)}
    out = []
    for i, view in enumerate(pair.seen_a.views.tolist()):
        j = index_b.get(view)
        if j is None or min(pair.seen_a.observed[i], pair.seen_b.observed[j]) < cfg.min_observed:
            continue
        w2c = pair.seen_a.world_to_camera[i]
        rr = relate(pair.a.features, pair.b.features, w2c[2, :3], cfg.tolerances, pair.contact,
                    cfg.margins)
        sources = ViewSources(pair.scene, view, pair.instances, (pair.a, pair.b),
                              np.stack([pair.seen_a.points[i], pair.seen_b.points[j]]), cfg)
        points, evidence, centres = {}, {}, {}
        for name, build in builders.items():
            clouds = build(sources)
            if clouds is None:
                continue
            points[name] = clouds.points
            if clouds.evidence is not None:
                evidence[name] = clouds.evidence
            if clouds.centres is not None:
                centres[name] = clouds.centres
        out.append(PairView(pair.scene, view, pair.seen_a.part_id, pair.seen_b.part_id,
                            pair.category, np.array(rr.truth, dtype=bool), rr.near_boundary(),
                            w2c, pair.scale, points, np.array(rr.near, dtype=bool), evidence,
                            centres))
    return out


def evidence_cloud(points: FloatArray, k: int) -> FloatArray:
    """At most k of a cloud's points, without repeats (seeded): the pair evidence's cloud.
    Repeated points would read as a spacing of zero."""
    pts = np.asarray(points)
    if len(pts) <= k:
        return pts
    return pts[np.sort(np.random.default_rng(0).choice(len(pts), k, replace=False))]


def k_points(points: FloatArray, k: int) -> Cloud:
    """k of a cloud's points (seeded; repeats where it has fewer), float32."""
    return np.asarray(sample_points(points, k, method="random"), dtype=np.float32)


def stack_inputs(views: Sequence[PairView], name: str) -> Cloud:
    """(N, 2, k, 3) float32 observer-frame points of one input over pair views that have it."""
    return np.stack([v.observer_points(name) for v in views if name in v.points])


@dataclass(frozen=True)
class PosedScene:
    """Parts whose true poses are known (part id -> part -> world, mm) and what a view of them
    is scored on: the labelled pairs, the parts' categories, the pairs' face-mate truth."""

    scene: str
    truth: Mapping[str, FloatArray]
    pairs: Sequence[tuple[str, str]]
    categories: Mapping[str, str]
    contacts: Mapping[tuple[str, str], PairContact]


def posed_pair_views(known: PosedScene, posed: Mapping[str, Mapping[str, FloatArray]],
                     cameras: Sequence[FloatArray], ws: Workspace,
                     cfg: PairConfig = DEFAULT_PAIRS,
                     sigmas: Mapping[str, Mapping[str, float]] | None = None,
                     turn_sigmas: Mapping[str, Mapping[str, float]] | None = None
                     ) -> list[PairView]:
    """Pair views of parts whose poses an input gives directly (a registration's): for every
    camera (world -> camera, metres) and labelled pair, the truth of the view from the parts'
    true poses and, per input of ``posed`` (part id -> pose), the CAD samples of each part at
    the input's pose (points, the evidence's samples with their faces' exact normals, the
    solids' centroids), world metres. A pair whose two parts an input has no pose for lacks
    that input; a view without any input for the pair gives none. ``sigmas``: per input, each
    pose's shift uncertainty (part id -> mm); a pair of that input is read within the two
    combined (``PairView.slack``), and a pose without a finite one at the CAD's tolerances;
    ``turn_sigmas`` likewise each pose's turn uncertainty (degrees, ``PairView.turn_slack``)."""
    scale = 1e-3
    placed = {pid: PosedPart(pid, {"pose_mm": pose}, ws, scale, cfg.n_points,
                              cfg.evidence_points) for pid, pose in known.truth.items()}
    inputs = {name: {pid: PosedPart(pid, {"pose_mm": pose}, ws, scale, cfg.n_points,
                                     cfg.evidence_points) for pid, pose in poses.items()}
              for name, poses in posed.items()}
    out = []
    for view, w2c in enumerate(cameras):
        for a, b in known.pairs:
            if a not in placed or b not in placed:
                continue
            rr = relate(placed[a].features, placed[b].features, w2c[2, :3], cfg.tolerances,
                        known.contacts.get((a, b), NO_CONTACT), cfg.margins)
            points, evidence, centres = {}, {}, {}
            slacks: dict[str, float] = {}
            turns: dict[str, float] = {}
            for name, parts in inputs.items():
                if a in parts and b in parts:
                    pa, pb = parts[a], parts[b]
                    points[name] = np.stack([pa.truth, pb.truth])
                    evidence[name] = (pa.dense, pb.dense)
                    centres[name] = np.stack([pa.centre, pb.centre])
                    slacks |= _slack(sigmas or {}, name, a, b)
                    turns |= _slack(turn_sigmas or {}, name, a, b)
            if points:
                out.append(PairView(known.scene, view, a, b, pair_category(
                    known.categories.get(a, "?"), known.categories.get(b, "?")),
                    np.array(rr.truth, dtype=bool), rr.near_boundary(), np.asarray(w2c),
                    scale, points, np.array(rr.near, dtype=bool), evidence, centres, slacks,
                    turns))
    return out


def _slack(sigmas: Mapping[str, Mapping[str, float]], name: str, a: str, b: str
           ) -> dict[str, float]:
    """The pair's slack in input ``name``: its two poses' sigmas combined; none where the
    input has no sigmas, 0 where either is not finite (the CAD's tolerances)."""
    if name not in sigmas:
        return {}
    pair = [sigmas[name].get(p, 0.0) for p in (a, b)]
    return {name: math.hypot(*pair) if all(map(math.isfinite, pair)) else 0.0}
