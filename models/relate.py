"""Relations of captured pairs by every method on every input, in one harness.

The relation stage of the nightly flow and the held-out evaluation of ``mateqa train
relations`` both come here. For each capture, the completion network's shape of every part in
every view is computed (``completed_clouds``: the shipped ``gan_lstm`` under the observed
protocol, one view at a time), the pair views are assembled with their per-view truth
(``cadio.evidence.pairs``), and each method decides the ten relations on each input:

- ``ltn`` and ``mlp``: the relation networks (one checkpoint per method and input), which see
  only the points in the observer's frame; a pair and its swap are decided together;
- ``geometric``: fixed tests on the pair's evidence from fitted planes and axes
  (``cadio.evidence.pair_features``), each the CAD definition widened by what points resolve.

One row per pair view x input x method x relation (``reports.relations.PAIR_COLUMNS``).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from cadio.capture.examples import OBSERVED, read_example
from cadio.capture.scan import ASSEMBLY_PREFIX
from cadio.errors import CaptureError
from cadio.evidence.pairs import DEFAULT_PAIRS, INPUTS, PairConfig, PairView, capture_pairs
from cadio.records import FloatArray, Relation
from cadio.workspace import Workspace, atomic_path
from models.errors import CheckpointError
from models.geometric import (
    ALL_EVIDENCE,
    OBSERVED_BY,
    GeometricTests,
    geometric_decisions,
    network_evidence,
    reads_observed,
    tests_for,
    with_observed,
)
from models.relation_decision import Decision, violations
from models.relations import RelationNet
from models.relations_train import (
    RelationData,
    load_relation_model,
    predict_relations,
)
from models.train import Model, predict
from reports.metrics import surface_points

if TYPE_CHECKING:
    from cadio.capture.observe import CubeGrid

log = logging.getLogger(__name__)

SHIPPED_RELATIONS = Path(__file__).resolve().parent / "checkpoints" / "relations"
LEARNED = ("ltn", "mlp")
METHODS = (*LEARNED, "geometric")
RELATIONS = tuple(r.value for r in Relation)
THRESHOLD = 0.5  # a voxel of the completion is solid above this probability
_SINGLE = re.compile(rf"^{OBSERVED}-(\d+)\.npz$")


@dataclass(frozen=True)
class RelationModels:
    """Loaded relation networks by (method, input), their temperatures and what each says."""

    models: dict[tuple[str, str], tuple[RelationNet, Decision]]
    cards: dict[tuple[str, str], dict[str, Any]]
    errors: tuple[str, ...] = ()  # checkpoints that could not be used, with the reason

    def trained_on(self) -> set[str]:
        """Part ids any network was trained on (never scored as held out)."""
        return {p for c in self.cards.values() for p in c.get("data", {}).get("train_parts", [])}

    def versions(self) -> dict[str, str]:
        return {f"{m}/{i}": f"step {c['step']}, code {c['code_version']}"
                for (m, i), c in sorted(self.cards.items())}


def load_relation_models(folder: Path = SHIPPED_RELATIONS) -> RelationModels:
    """Every relation checkpoint (``<method>-<input>.pt``) of a folder; none when absent. A
    checkpoint that does not load is left out with its reason (the baseline still runs)."""
    models, cards, errors = {}, {}, []
    for path in sorted(Path(folder).glob("*.pt")) if Path(folder).is_dir() else []:
        try:
            model, decision, ckpt = load_relation_model(path)
        except CheckpointError as exc:
            errors.append(f"{path.name}: {exc.reason.splitlines()[0]}")
            log.error("relation checkpoint %s left out: %s", path, exc.reason.splitlines()[0])
            continue
        stale = _stale_evidence(ckpt)
        if stale:
            errors.append(f"{path.name}: {stale}")
            log.error("relation checkpoint %s left out: %s", path, stale)
            continue
        key = (str(ckpt["method"]), str(ckpt["data"].get("input", "")))
        models[key] = (model, decision)
        cards[key] = {k: v for k, v in ckpt.items() if k != "state_dict"}
    return RelationModels(models, cards, tuple(errors))


def _stale_evidence(ckpt: Mapping[str, Any]) -> str:
    """Why a checkpoint cannot read this code's pair evidence ("" when it can): it was trained
    on another vector (its names, where it lists them, or its width)."""
    from cadio.evidence.pair_features import PAIR_FEATURES

    width = int(ckpt["config"].get("pair_features", 0))
    names = [str(n) for n in ckpt["data"].get("pair_features") or []]
    ours = len(PAIR_FEATURES)
    # A checkpoint that names its columns reads them by name (the evidence is only ever
    # appended to); one that names none reads the first ``width``, so it must be all of them.
    if width == 0 or (not names and width == ours) \
            or (names and set(names) <= set(ALL_EVIDENCE)
                and names == list(ckpt["config"].get("evidence") or names[:width])):
        return ""
    return (f"trained on {width} pair features, this code measures {len(PAIR_FEATURES)}: "
            "retrain it (mateqa train relations)")


Surface = Callable[[npt.NDArray[np.float32], "CubeGrid"], FloatArray]


def voxel_surface(probs: npt.NDArray[np.float32], grid: CubeGrid) -> FloatArray:
    """The centres of the surface voxels of the solid predicted (probabilities over ``grid``,
    (n, n, n)), world metres: how the night reads a completion."""
    n = probs.shape[-1]
    return surface_points(probs > THRESHOLD, grid.voxel_m(n), grid.grid_to_world(n))


def completed_clouds(folder: Path, model: Model, surface: Surface = voxel_surface
                     ) -> dict[int, FloatArray]:
    """The completion of each single observed view of one part: view -> (m, 3) world metres
    (``surface`` of the probabilities predicted in the view's observed grid; the scan's points
    where nothing is predicted)."""
    files = sorted((int(m.group(1)), p) for p in Path(folder).glob(f"{OBSERVED}-*.npz")
                   if (m := _SINGLE.match(p.name)))
    if not files:
        return {}
    examples = [read_example(p) for _, p in files]
    probs = predict(model, [e.inputs for e in examples], batch_size=16)
    out = {}
    for (view, _), example, p in zip(files, examples, probs, strict=True):
        pts = surface(p, example.grid) if (p > THRESHOLD).any() else \
            example.points  # nothing predicted: the scan is all there is
        out[view] = np.asarray(pts, dtype=np.float64)
    return out


def capture_completions(capture: str, part_ids: Iterable[str], ws: Workspace,
                        model: Model | None, surface: Surface = voxel_surface
                        ) -> dict[tuple[str, int], FloatArray]:
    """(part id, view) -> completed points for the parts of one capture (none without model)."""
    if model is None:
        return {}
    return {(pid, view): pts for pid in part_ids
            for view, pts in completed_clouds(ws.inputs(capture, pid), model, surface).items()}


def decide(points: npt.NDArray[np.float32], mm_per_unit: npt.NDArray[Any], method: str,
           model: tuple[RelationNet, Decision] | None,
           keys: Sequence[tuple[Any, Any]] | None = None,
           features: npt.NDArray[np.float32] | None = None,
           centres: npt.NDArray[np.floating] | None = None,
           tests: GeometricTests | None = None,
           observed: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]] | None = None
           ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.float64],
                      npt.NDArray[np.bool_], list[str]] | None:
    """One method's (decided, confidence, violation), each (N, 10), and joint (N,) on
    observer-frame pairs (N, 2, k, 3); None for a learned method without its checkpoint.
    ``features``: the pairs' raw evidence (``pair_features_many``), computed here when None.
    ``centres``: (N, 2, 3) the parts' centres in the frame of ``points`` where the input knows
    the solids (``truth``); None: the points' means. ``tests``: the input's geometric tests
    (``models.geometric.tests_for``; None: the fitted points'), decided by ``geometric`` and
    read by the networks. ``observed``: the same views' observed points (N, 2, k, 3) and
    their ``network_evidence``, which a network of an input in ``OBSERVED_BY`` reads in
    place of ``points`` and beside its own evidence (None for such a network without them,
    as without its checkpoint).

    The joint is the network's joint head's answer; ``geometric``, and a network trained
    without a joint head, read it from their concentric and coincident answers
    (``cadio.truth.joints.predicted_joint``)."""
    from cadio.evidence.pair_features import pair_features_many

    if features is None:
        features = pair_features_many(points, mm_per_unit, list(keys) if keys else None)
    tests = tests or GeometricTests()
    if method == "geometric":
        decided = geometric_decisions(points, mm_per_unit, features, keys, tests, centres)
        # the tests are symmetric and the cones converse: nothing to violate; a hard
        # geometric decision carries no calibrated probability.
        return (decided, np.full(decided.shape, np.nan), np.zeros(decided.shape, dtype=bool),
                joints_of(decided))
    if model is None or (observed is None and reads_observed(model[0].cfg.evidence)):
        return None
    net, decision = model
    evidence = network_evidence(features, points, centres, tests)
    if observed is not None and reads_observed(net.cfg.evidence):
        points, evidence = observed[0], with_observed(evidence, observed[1])
    data = RelationData(points, np.zeros((len(points), len(RELATIONS)), dtype=bool),
                        np.asarray(mm_per_unit, dtype=np.float64), evidence)
    pred = predict_relations(net, data, decision=decision)
    return (pred.decided, pred.confidence, violations(pred.raw_ab, pred.raw_ba),
            pred.joint() or joints_of(pred.decided))


def joints_of(decided: npt.NDArray[np.bool_]) -> list[str]:
    """The joint each pair's concentric and coincident answers imply (N,)."""
    from cadio.truth.joints import predicted_joint

    return [predicted_joint(bool(c), bool(k)) for c, k in
            zip(decided[:, RELATIONS.index("concentric")],
                decided[:, RELATIONS.index("coincident")], strict=True)]


def relate_views(views: Sequence[PairView], models: RelationModels,
                 methods: Sequence[str] = METHODS) -> list[dict[str, Any]]:
    """``relations_pairs`` rows of pair views: every method on every input they carry (the
    networks of an input in ``OBSERVED_BY`` where the views carry the observed points too)."""
    from cadio.evidence.pair_features import pair_features_many

    rows: list[dict[str, Any]] = []
    # observed input -> id(view) -> the view's points and network evidence of that input
    seen: dict[str, dict[int, tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]]] = {}
    for name in INPUTS:
        having = [v for v in views if name in v.points]
        if not having:
            continue
        points = np.stack([v.observer_points(name) for v in having])
        mm = np.array([1.0 / v.scale_m_per_mm for v in having])
        keys = [((v.scene, v.part_a, v.view), (v.scene, v.part_b, v.view)) for v in having]
        # the evidence is measured on each view's evidence clouds (CAD samples: one per part)
        cloud_keys = [((v.scene, v.part_a), (v.scene, v.part_b)) if name == "truth" else k
                      for v, k in zip(having, keys, strict=True)]
        features = pair_features_many([v.evidence_clouds(name) for v in having], mm,
                                      cloud_keys)
        centres = np.stack([v.observer_centres(name) for v in having])
        if name in OBSERVED_BY.values():  # kept for the networks of the inputs that read it
            own = network_evidence(features, points, centres, tests_for(name))
            seen[name] = {id(v): (p, e) for v, p, e in zip(having, points, own, strict=True)}
        reads = seen.get(OBSERVED_BY.get(name, ""), {})
        observed = None
        if all(id(v) in reads for v in having):
            observed = (np.stack([reads[id(v)][0] for v in having]),
                        np.stack([reads[id(v)][1] for v in having]))
        for method in methods:
            decided = decide(points, mm, method, models.models.get((method, name)), keys,
                             features, centres, tests_for(name), observed)
            if decided is not None:
                rows += _rows(having, name, method, *decided)
    return rows


def _rows(views: Sequence[PairView], name: str, method: str, decided: npt.NDArray[np.bool_],
          confidence: npt.NDArray[np.float64], broken: npt.NDArray[np.bool_],
          joints: Sequence[str]) -> list[dict[str, Any]]:
    return [{"scene": v.scene, "view": v.view, "part_a": v.part_a, "part_b": v.part_b,
             "category": v.category, "input": name, "method": method, "relation": rel,
             "truth": bool(v.labels[k]), "predicted": bool(decided[i, k]),
             "confidence": float(confidence[i, k]), "near_boundary": v.near_boundary,
             "violation": bool(broken[i, k]), "joint": joints[i]}
            for i, v in enumerate(views) for k, rel in enumerate(RELATIONS)]


def relate_captures(captures: Sequence[Path], ws: Workspace, categories: Mapping[str, str],
                    models: RelationModels, completion: Model | None,
                    cfg: PairConfig = DEFAULT_PAIRS) -> tuple[list[dict[str, Any]], list[str]]:
    """Rows of every capture's pair views, and one line per capture that failed (the others
    go on)."""
    rows: list[dict[str, Any]] = []
    failed = []
    for path in captures:
        try:
            views = capture_pairs(path, ws, categories, cfg, completions_of(path, ws, completion))
        except (OSError, ValueError, KeyError, CaptureError) as exc:
            failed.append(f"{path.name}: {type(exc).__name__}: {exc}")
            continue
        rows += relate_views(views, models)
    return rows, failed


def completions_of(path: Path, ws: Workspace, completion: Model | None,
                   surface: Surface = voxel_surface) -> dict[tuple[str, int], FloatArray]:
    """(part id, view) -> completed points of every part with inputs under a capture."""
    folder = ws.root / "inputs" / path.stem
    parts = [p.name for p in folder.iterdir() if p.is_dir()] if folder.is_dir() else []
    return capture_completions(path.stem, parts, ws, completion, surface)


@dataclass(frozen=True)
class RelateBatch:
    """What ``relate_batch`` wrote: the rows' parquet, its pair views and failures."""

    path: str
    captures: int
    pair_views: int
    rows: int
    failed: tuple[str, ...]
    joints_path: str = ""
    left_out: int = 0  # pair views not scored: a network trained on one of their parts


def relate_batch(captures: Sequence[Path], ws: Workspace, relations_dir: Path,
                 completion_dir: Path, out: Path, cfg: PairConfig = DEFAULT_PAIRS) -> RelateBatch:
    """The relation stage for a batch of captures: rows of every method on every input,
    written to ``out`` (parquet); pairs with a part that the relation or the completion
    networks trained on are left out (their scores would not be held out)."""
    from cadio.catalog import read_catalog
    from models.evaluate import load_models
    from reports.relations import pairs_frame

    catalog = read_catalog(ws.catalog)
    categories = dict(zip(catalog["part_id"].astype(str), catalog["category"].astype(str),
                          strict=True))
    models = load_relation_models(relations_dir)
    completions = load_models(completion_dir)
    completion = completions.models.get(("gan_lstm", OBSERVED))
    rows, failed = relate_captures(captures, ws, categories, models, completion, cfg)
    failed = [*models.errors, *failed]
    seen = models.trained_on() | completions.trained_on()  # a part a network learned from
    held = [r for r in rows if r["part_a"] not in seen and r["part_b"] not in seen]
    frame = pairs_frame(held)
    left_out = len({_view_key(r) for r in rows} - {_view_key(r) for r in held})
    joints = out.with_name(f"{out.stem}-joints.parquet")
    with atomic_path(joints) as tmp:  # the joints first: the rows' file marks the batch done
        cad_joints(captures, ws).to_parquet(tmp, index=False)
    with atomic_path(out) as tmp:
        frame.to_parquet(tmp, index=False)
    views = frame[["scene", "view", "part_a", "part_b"]].drop_duplicates()
    return RelateBatch(str(out), len(captures), len(views), len(frame), tuple(failed),
                       str(joints), left_out)


def _view_key(row: Mapping[str, Any]) -> tuple[Any, ...]:
    return row["scene"], row["view"], row["part_a"], row["part_b"]


def cad_joints(captures: Sequence[Path], ws: Workspace) -> pd.DataFrame:
    """The CAD's joints (scene, part_a, part_b, kinematic) of the assembly captures."""
    frames = []
    for path in captures:
        if not path.stem.startswith(ASSEMBLY_PREFIX):
            continue
        mates = ws.mates(path.stem[len(ASSEMBLY_PREFIX):])
        if mates.exists():
            table = pd.read_parquet(mates, columns=["part_a", "part_b", "level", "kinematic"])
            joint = table[table["level"] == "joint"].drop(columns="level")
            frames.append(joint.assign(scene=path.stem))
    columns = ["scene", "part_a", "part_b", "kinematic"]
    return pd.concat(frames)[columns] if frames else pd.DataFrame(columns=columns)
