"""Relations of captured pairs by every method on every input, in one harness.

The relation stage of the nightly flow and the held-out evaluation of ``mateqa train
relations`` both come here. For each capture, the pair views are assembled with their per-view
truth (``cadio.evidence.pairs``) in every registered input (``models.relation_inputs``: each
input's builder makes its clouds, the ``completed`` one from the night's completion network),
and every registered method (``models.relation_methods``) decides the ten relations on each
input: the networks (one checkpoint per method and input, which see only the points in the
observer's frame; a pair and its swap are decided together), and the methods without learning
(fixed tests on the pair's evidence, ``cadio.evidence.pair_features``).

One row per pair view x input x method x relation (``reports.relations.PAIR_COLUMNS``).
"""

from __future__ import annotations

import logging
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from cadio.capture.examples import OBSERVED
from cadio.capture.scan import ASSEMBLY_PREFIX, assembly_pairs
from cadio.catalog import read_catalog
from cadio.errors import CaptureError
from cadio.evidence.pairs import DEFAULT_PAIRS, PairConfig, PairView, capture_pairs
from cadio.records import Relation
from cadio.sandbox import Job, Limits, run_isolated
from cadio.workspace import Workspace, atomic_path
from models.completions import ours as completion_ours
from models.errors import CheckpointError
from models.geometric import (
    ALL_EVIDENCE,
    GeometricTests,
    network_evidence,
    reads_observed,
    tests_for,
    with_observed,
    within_pose,
)
from models.relation_decision import Decision, violations
from models.relation_inputs import INPUTS, InputContext, builders
from models.relation_methods import RELATION_METHODS, RelationMethod, decide_fixed
from models.relations import RelationNet
from models.relations_train import (
    RelationData,
    load_relation_model,
    nearest_of_pairs,
    predict_relations,
)

log = logging.getLogger(__name__)

SHIPPED_RELATIONS = Path(__file__).resolve().parent / "checkpoints" / "relations"
RELATIONS = tuple(r.value for r in Relation)


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


def reading_digest() -> str:
    """SHA-256 of the code that reads pair views into relation rows (this module, the pair
    views and the geometric tests, which read a registration's poses within their
    uncertainty): a night's cached relations are redone when it changes, as its evidence's
    are (``evidence_digest``)."""
    import hashlib

    from cadio.evidence import pairs
    from models import geometric

    digest = hashlib.sha256()
    for source in (__file__, pairs.__file__, geometric.__file__):
        digest.update(Path(source or "").read_bytes())
    return digest.hexdigest()


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


Observed = tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]
Decided = tuple[npt.NDArray[np.bool_], npt.NDArray[np.float64], npt.NDArray[np.bool_], list[str]]


@dataclass(frozen=True)
class PairBatch:
    """One input's pair views as the methods read them.

    points: (N, 2, k, 3) observer-frame points; mm_per_unit: (N,). keys: per row a key of each
    part's cloud (a cloud met again is measured once). features: the pairs' raw evidence
    (``pair_features_many``; None: measured on ``points``). centres: (N, 2, 3) the parts'
    centres where the input knows the solids (None: the points' means). tests: the input's
    geometric tests (``models.geometric.tests_for``), decided by the methods without learning
    and read by the networks. observed: the same views' observed points (N, 2, k, 3) and
    their ``network_evidence``, which a network of an input that reads them
    (``RelationInput.observed_by``) reads in place of ``points`` and beside its own evidence.
    """

    points: npt.NDArray[np.float32]
    mm_per_unit: npt.NDArray[Any]
    keys: Sequence[tuple[Any, Any]] | None = None
    features: npt.NDArray[np.float32] | None = None
    centres: npt.NDArray[np.floating] | None = None
    tests: GeometricTests = field(default_factory=GeometricTests)
    observed: Observed | None = None
    # per set of points a network reads (by id, the array kept with it): each point's distance
    # to the other part's nearest, measured once for every network of the batch
    _near: dict[int, tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]] = field(
        default_factory=dict, repr=False, compare=False)

    def nearest(self, points: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        """(N, 2, k) ``nearest_of_pairs`` of ``points`` (the batch's or its observed ones),
        measured once for each distinct pair of clouds."""
        held = self._near.get(id(points))
        if held is None or held[0] is not points:
            mm = np.asarray(self.mm_per_unit, dtype=np.float64)
            first, back = distinct_rows(points, mm)
            held = (points, nearest_of_pairs(np.asarray(points[first], dtype=np.float32),
                                             mm[first])[back])
            self._near[id(points)] = held
        return held[1]

    def evidence(self) -> npt.NDArray[np.float32]:
        """The raw evidence (measured here where the batch carries none)."""
        from cadio.evidence.pair_features import pair_features_many

        if self.features is not None:
            return self.features
        keys = list(self.keys) if self.keys else None
        return pair_features_many(self.points, self.mm_per_unit, keys)


def decide(batch: PairBatch, method: RelationMethod | str,
           model: tuple[RelationNet, Decision] | None) -> Decided | None:
    """One method's (decided, confidence, violation), each (N, 10), and joint (N,) on a batch
    of pair views; None for a network without its checkpoint, or for one that reads the
    observed points where the batch carries none.

    The joint is the network's joint head's answer; a method without learning, and a network
    trained without a joint head, read it from their concentric and coincident answers
    (``cadio.truth.joints.predicted_joint``)."""
    spec = RELATION_METHODS.get(method) if isinstance(method, str) else method
    features = batch.evidence()
    if not spec.learned:
        decided = decide_fixed(spec, batch.points, batch.mm_per_unit, features, batch.keys,
                               batch.tests, batch.centres)
        # the tests are symmetric and the cones converse: nothing to violate; a hard
        # geometric decision carries no calibrated probability.
        return (decided, np.full(decided.shape, np.nan), np.zeros(decided.shape, dtype=bool),
                joints_of(decided))
    if model is None or (batch.observed is None and reads_observed(model[0].cfg.evidence)):
        return None
    net, decision = model
    points = batch.points
    evidence = network_evidence(features, points, batch.centres, batch.tests)
    if batch.observed is not None and reads_observed(net.cfg.evidence):
        points, evidence = batch.observed[0], with_observed(evidence, batch.observed[1])
    mm = np.asarray(batch.mm_per_unit, dtype=np.float64)
    # the network decides each distinct input once: an exact input's clouds (CAD samples at
    # a pose) are the same in every view of a pair, and so are their evidence
    first, back = distinct_rows(points, evidence, mm)
    data = RelationData(points[first], np.zeros((len(first), len(RELATIONS)), dtype=bool),
                        mm[first], evidence[first], batch.nearest(points)[first])
    pred = predict_relations(net, data, decision=decision)
    joints = pred.joint()
    decided = pred.decided[back]
    return (decided, pred.confidence[back], violations(pred.raw_ab[back], pred.raw_ba[back]),
            [joints[i] for i in back] if joints is not None else joints_of(decided))


def distinct_rows(*arrays: npt.NDArray[Any]) -> tuple[npt.NDArray[np.int64],
                                                      npt.NDArray[np.int64]]:
    """The rows that are distinct across ``arrays`` (each (N, ...), read row by row) and
    where each row is among them: (first, back) with ``a[first][back]`` row for row ``a``
    for every array, ``first`` ascending (each distinct row's first occurrence)."""
    import hashlib

    n = len(arrays[0])
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    rows = [np.ascontiguousarray(a).reshape(n, -1).view(np.uint8).reshape(n, -1)
            for a in arrays]
    keys = [hashlib.blake2b(b"".join(r[i].tobytes() for r in rows), digest_size=16).digest()
            for i in range(n)]
    at: dict[bytes, int] = {}
    first: list[int] = []
    back = np.empty(n, dtype=np.int64)
    for i, key in enumerate(keys):
        if key not in at:
            at[key] = len(first)
            first.append(i)
        back[i] = at[key]
    return np.asarray(first, dtype=np.int64), back


def joints_of(decided: npt.NDArray[np.bool_]) -> list[str]:
    """The joint each pair's concentric and coincident answers imply (N,)."""
    from cadio.truth.joints import predicted_joint

    return [predicted_joint(bool(c), bool(k)) for c, k in
            zip(decided[:, RELATIONS.index("concentric")],
                decided[:, RELATIONS.index("coincident")], strict=True)]


def relate_views(views: Sequence[PairView], models: RelationModels,
                 methods: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """``relations_pairs`` rows of pair views: every method (default: every registered one)
    on every input they carry (the networks of an input that reads another's observed points,
    ``RelationInput.observed_by``, where the views carry those too)."""
    from cadio.evidence.pair_features import pair_features_many

    chosen = [RELATION_METHODS.get(m) for m in methods or RELATION_METHODS.names()]
    rows: list[dict[str, Any]] = []
    # input -> id(view) -> the view's points and network evidence of that input
    seen: dict[str, dict[int, tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]]] = {}
    observers = {i.observed_by for i in INPUTS.entries() if i.observed_by}
    # the exact inputs' clouds (CAD samples at a pose) are the same in every view of a pair,
    # and in every input that gives the part the same pose (a registration's poses read at
    # its uncertainty and at the CAD's tolerances): each distinct pair is measured once
    content: dict[int, tuple[npt.NDArray[Any], str]] = {}
    measured: dict[tuple[Hashable, Hashable], npt.NDArray[np.float32]] = {}
    for spec in INPUTS.entries():
        name = spec.name
        having = [v for v in views if name in v.points]
        if not having:
            continue
        points = np.stack([v.observer_points(name) for v in having])
        mm = np.array([1.0 / v.scale_m_per_mm for v in having])
        keys = [((v.scene, v.part_a, v.view), (v.scene, v.part_b, v.view)) for v in having]
        clouds = [v.evidence_clouds(name) for v in having]
        cloud_keys = [(_content_key(a, m, content), _content_key(b, m, content)) if spec.exact
                      else k for (a, b), m, k in zip(clouds, mm, keys, strict=True)]
        features = pair_features_many(clouds, mm, cloud_keys,
                                      memo=measured if spec.exact else None)
        slack = np.array([v.slack.get(name, 0.0) for v in having])
        turn = np.array([v.turn_slack.get(name, 0.0) for v in having])
        if slack.any() or turn.any():  # a registration's poses: read within their uncertainty
            features = within_pose(features, slack, turn)
        centres = np.stack([v.observer_centres(name) for v in having])
        if name in observers:  # kept for the networks of the inputs that read it
            own = network_evidence(features, points, centres, tests_for(name))
            seen[name] = {id(v): (p, e) for v, p, e in zip(having, points, own, strict=True)}
        reads = seen.get(spec.observed_by or "", {})
        observed = None
        if all(id(v) in reads for v in having):
            observed = (np.stack([reads[id(v)][0] for v in having]),
                        np.stack([reads[id(v)][1] for v in having]))
        batch = PairBatch(points, mm, keys, features, centres, tests_for(name), observed)
        for method in chosen:
            decided = decide(batch, method, models.models.get((method.name, spec.checkpoints)))
            if decided is not None:
                rows += _rows(having, name, method.name, *decided)
    return rows


def _content_key(cloud: npt.NDArray[Any], mm_per_unit: float,
                 known: dict[int, tuple[npt.NDArray[Any], str]]) -> Hashable:
    """A key of a cloud by its content and scale: a digest, kept per array in ``known`` (one
    input's pair views share its parts' arrays; the array is kept with it, so that its id
    names it while the digest is kept)."""
    import hashlib

    held = known.get(id(cloud))
    if held is None or held[0] is not cloud:
        data = np.ascontiguousarray(cloud)
        held = (cloud, f"{data.shape}:{data.dtype}:"
                + hashlib.blake2b(data.tobytes(), digest_size=16).hexdigest())
        known[id(cloud)] = held
    return (held[1], float(mm_per_unit))


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
                    models: RelationModels, ctx: InputContext,
                    cfg: PairConfig = DEFAULT_PAIRS) -> tuple[list[dict[str, Any]], list[str]]:
    """Rows of every capture's pair views in every registered input, and one line per capture
    that failed (the others go on)."""
    rows: list[dict[str, Any]] = []
    failed = []
    for path in captures:
        try:
            views = capture_pairs(path, ws, categories, cfg, builders(path, ws, ctx))
        except (OSError, ValueError, KeyError, CaptureError) as exc:
            failed.append(f"{path.name}: {type(exc).__name__}: {exc}")
            continue
        rows += relate_views(views, models)
    return rows, failed


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


@dataclass(frozen=True)
class RelateJob:
    """One batch of the relation stage, as a worker process runs it."""

    captures: tuple[str, ...]
    workspace: str
    relations_dir: str
    completion_dir: str
    out: str
    # the methods and inputs registered outside their packages (``Registry.foreign``)
    methods: tuple[RelationMethod, ...] = ()
    inputs: tuple[Any, ...] = ()


def relate_job(job: RelateJob) -> RelateBatch:
    with RELATION_METHODS.including(job.methods), INPUTS.including(job.inputs):
        return relate_batch([Path(c) for c in job.captures], Workspace(Path(job.workspace)),
                            Path(job.relations_dir), Path(job.completion_dir), Path(job.out))


# As the completion's batches (``models.evaluate.ISOLATED``): a worker process each, on one
# thread of its libraries, so that two batches run on two cores.
ISOLATED = Limits(seconds=3600.0, memory_mb=8192, workers=1, threads=1)


def relate_isolated(captures: Sequence[Path], ws: Workspace, relations_dir: Path,
                    completion_dir: Path, out: Path, limits: Limits = ISOLATED) -> RelateBatch:
    """``relate_batch`` in a worker process (``cadio.sandbox``); a worker that dies or runs
    out of time fails each of the batch's captures, with the reason, and writes no rows."""
    job = RelateJob(tuple(str(c) for c in captures), str(ws.root), str(relations_dir),
                    str(completion_dir), str(out), RELATION_METHODS.foreign(), INPUTS.foreign())
    (outcome,) = run_isolated(relate_job, [Job(str(out), job)], limits)
    if outcome.result is not None:
        return outcome.result
    log.warning("relations of %d captures: %s", len(captures), outcome.error)
    return RelateBatch(str(out), len(captures), 0, 0, tuple(
        f"{Path(c).name}: relation worker: {outcome.error}" for c in captures))


def relate_batch(captures: Sequence[Path], ws: Workspace, relations_dir: Path,
                 completion_dir: Path, out: Path, cfg: PairConfig = DEFAULT_PAIRS) -> RelateBatch:
    """The relation stage for a batch of captures: rows of every method on every input,
    written to ``out`` (parquet); pairs with a part that the relation or the completion
    networks trained on are left out (their scores would not be held out)."""
    from models.evaluate import load_models
    from reports.relations import pairs_frame

    catalog = read_catalog(ws.catalog)
    categories = dict(zip(catalog["part_id"].astype(str), catalog["category"].astype(str),
                          strict=True))
    models = load_relation_models(relations_dir)
    completions = load_models(completion_dir)
    completion = completions.models.get((completion_ours().name, OBSERVED))
    rows, failed = relate_captures(captures, ws, categories, models,
                                   InputContext(completion=completion), cfg)
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


@dataclass(frozen=True)
class RelateInspectionJob:
    """An inspected assembly's relations, as a worker process runs them."""

    folder: str
    workspace: str
    relations_models: str


def relate_inspection_job(job: RelateInspectionJob) -> pd.DataFrame:
    """``relate_inspection`` with the models of ``job.relations_models`` (in a worker whose
    threads its ``cadio.sandbox.Limits`` set)."""
    return relate_inspection(Path(job.folder), Workspace(Path(job.workspace)),
                             load_relation_models(Path(job.relations_models)))


def _scored(found: pd.DataFrame) -> pd.DataFrame:
    """The search's segments as their relations are scored: each as the part the inspection
    scored it as (``cadio.inspect.stage.scored_as``: its own part where that is of the shape
    it was registered as; copies of a shape are interchangeable), at its pose read as that
    part's; tables without those columns as named."""
    if "scored_index" not in found.columns:
        return found
    out = found[found["scored_index"].astype(int) >= 0].copy()
    out["index"] = out["scored_index"].astype(int)
    out["pose"] = out["scored_pose"]
    return out


def relate_inspection(folder: Path, ws: Workspace, models: RelationModels,
                      cfg: PairConfig = DEFAULT_PAIRS) -> pd.DataFrame:
    """The relations of an inspected assembly's intact capture: every method on the
    ``registered`` input (the CAD at the poses the search route found without the design, each
    pair read within its poses' uncertainty; copies of a shape scored as the part whose points
    they registered: ``_scored``), on ``registered_cad`` (the same poses at the
    CAD's tolerances) and on ``truth`` (the CAD where the parts stood), on the same pair views,
    for each set of views the capture was inspected with (scene ``<capture>`` for all views,
    ``<capture>@<view>`` for one alone). Rows of ``reports.relations.PAIR_COLUMNS``."""
    from cadio.evidence.pairs import PosedScene, posed_pair_views
    from cadio.inspect.evaluate import read_tables
    from cadio.inspect.stage import ALL_VIEWS, part_ids, read_truth
    from cadio.recordings.mcap_io import read_capture
    from cadio.truth.relations import contacts_of_mates

    found = read_tables(folder)["found"]
    if found.empty:
        return pd.DataFrame()
    rows: list[dict[str, Any]] = []
    for (capture, views), group in found.groupby(["capture", "views"], sort=True):
        truth = read_truth(ws, str(capture))
        mates = pd.read_parquet(ws.mates(str(truth["assembly"])))
        ids = dict(enumerate(part_ids(str(truth["assembly"]), ws)))
        cameras = [f.world_to_camera for f in read_capture(ws.capture(str(capture)))]
        if views != ALL_VIEWS:
            cameras = [cameras[int(views)]]
        catalog = read_catalog(ws.catalog)
        known = PosedScene(
            str(capture) if views == ALL_VIEWS else f"{capture}@{views}",
            {ids[int(i)]: np.array(p) for i, p in truth["poses"].items() if int(i) in ids},
            [(a, b) for a, b in assembly_pairs(mates)],
            dict(zip(catalog["part_id"].astype(str), catalog["category"].astype(str),
                     strict=True)),
            contacts_of_mates(mates.to_dict("records"), mates.attrs.get("near_boundary", [])))
        scored = _scored(group)
        mine = scored[scored["index"].astype(int).isin(ids)]
        registered = {ids[int(r.index)]: np.array(r.pose).reshape(4, 4)
                      for r in mine.itertuples()}
        named = [ids[int(i)] for i in mine["index"]]
        sigma = {column: dict(zip(named, mine.get(column, pd.Series(0.0, index=mine.index))
                                  .astype(float), strict=True))
                 for column in ("sigma_mm", "sigma_deg")}
        views_of = posed_pair_views(
            known, {"registered": registered, "registered_cad": registered,
                    "truth": dict(known.truth)}, cameras, ws, cfg,
            {"registered": sigma["sigma_mm"]}, {"registered": sigma["sigma_deg"]})
        rows += relate_views(views_of, models)
    return pd.DataFrame(rows)
