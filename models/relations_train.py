"""Training, calibration, inference and checkpoints of the relation network (``ltn``, ``mlp``).

``train_relations`` runs ``cfg.steps`` Adam steps on loss = 1 - satisfaction of the knowledge
base, seeded throughout; each step's batch, point subsets, jitter and swaps are pure functions
of (seed, step). Every ``eval_every`` steps it scores the validation pairs and keeps the best
weights by the mean over relations of the F1 at thresholds fitted on those pairs (mean accuracy
would let the six directional relations, frequent and easy, hide the rare ones). A joint head's
answers do not enter the choice: weighing its balanced accuracy in as an eleventh term chose
earlier steps whose relations scored 0.01-0.04 less mean F1 on validation. It then fits,
per relation, the decision threshold that maximises F1 on validation (the fact axioms weigh a
rare relation's positives and negatives alike, so a score of 0.5 over-predicts it) and a
temperature about that threshold (converse relations share both, so a pair and its swap get the
same decisions and confidences), and returns a self-describing checkpoint.
``predict_relations`` gives raw outputs for both orders, consistent decisions and calibrated
confidences.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from models.checkpoint import (
    FORMAT,
    KEYS,
    Checkpoint,
    code_version,
    load_checkpoint,
    save_checkpoint,
)
from models.checkpoint import state_copy as _state_copy
from models.errors import CheckpointError
from models.relation_decision import (
    Decision,
    calibrate,
    combine,
    decide,
    f1_scores,
    fit_temperatures,
    fit_thresholds,
    swap_decision,
    violations,
)
from models.relation_logic import joint_knowledge_base, knowledge_base
from models.relation_methods import learned
from models.relations import (
    JOINTS,
    RELATIONS,
    RelationConfig,
    RelationNet,
)
from models.train import TrainEvent, seeded
from reports.relations import expected_calibration_error

logger = logging.getLogger(__name__)

RELATION_KEYS = ("temperatures",)  # beyond the completion checkpoints' keys


@dataclass(frozen=True, eq=False)
class RelationData:
    """Labelled part pairs.

    points: (N, 2, P, 3) float32, the two parts' clouds in the observer's frame, any unit.
    labels: (N, 10) bool, the relations of the ordered pair (a, b) in ``Relation`` order.
    mm: (N,) millimetres of the parts per unit of ``points`` (default 1: points in mm).
    features: (N, F) float32 pair evidence as the networks read it
        (``models.geometric.network_evidence``), or None; symmetric in the two parts but for
        the pair's direction (``models.geometric.swap_evidence``).
    near: (N, 2, P) float32, each point's distance to the other part's nearest point in mm;
        computed here when None.
    joints: (N,) int64, each pair's kinematic joint as an index into ``JOINTS``, -1 where
        unknown; None: no joint labels (a joint head then learns nothing).
    """

    points: npt.NDArray[np.float32]
    labels: npt.NDArray[np.bool_]
    mm: npt.NDArray[np.float64] | None = None
    features: npt.NDArray[np.float32] | None = None
    near: npt.NDArray[np.float32] | None = None
    joints: npt.NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        points = np.asarray(self.points, dtype=np.float32)
        labels = np.asarray(self.labels).astype(bool)
        if points.ndim != 4 or points.shape[1:2] + points.shape[3:] != (2, 3):
            raise ValueError(f"points must be (N, 2, P, 3); got {points.shape}")
        if labels.shape != (len(points), len(RELATIONS)):
            raise ValueError(f"labels must be ({len(points)}, 10); got {labels.shape}")
        mm = np.ones(len(points)) if self.mm is None else np.asarray(self.mm, dtype=np.float64)
        if mm.shape != (len(points),):
            raise ValueError(f"mm must be ({len(points)},); got {mm.shape}")
        if self.features is not None:
            feats = np.asarray(self.features, dtype=np.float32)
            if feats.ndim != 2 or len(feats) != len(points):
                raise ValueError(f"features must be ({len(points)}, F); got {feats.shape}")
            object.__setattr__(self, "features", feats)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "mm", mm)
        near = nearest_of_pairs(points, mm) if self.near is None else np.asarray(
            self.near, dtype=np.float32)
        if near.shape != points.shape[:3]:
            raise ValueError(f"near must be {points.shape[:3]}; got {near.shape}")
        object.__setattr__(self, "near", near)
        if self.joints is not None:
            joints = np.asarray(self.joints, dtype=np.int64)
            if joints.shape != (len(points),) or joints.min(initial=0) < -1 \
                    or joints.max(initial=0) >= len(JOINTS):
                raise ValueError(f"joints must be ({len(points)},) in [-1, {len(JOINTS)})")
            object.__setattr__(self, "joints", joints)

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, rows: npt.NDArray[np.bool_] | npt.NDArray[np.int64]) -> RelationData:
        assert self.mm is not None and self.near is not None
        return RelationData(self.points[rows], self.labels[rows], self.mm[rows],
                            None if self.features is None else self.features[rows],
                            self.near[rows], None if self.joints is None else self.joints[rows])

    def swapped(self) -> RelationData:
        """The pairs (b, a), labelled by the rules, their evidence swapped."""
        from models.geometric import swap_evidence

        assert self.near is not None
        return RelationData(self.points[:, ::-1].copy(), swap_decision(self.labels), self.mm,
                            None if self.features is None else swap_evidence(self.features),
                            self.near[:, ::-1].copy(), self.joints)

    def tensors(self, rows: slice | npt.NDArray[np.int64]) -> tuple[torch.Tensor, ...]:
        """(points, mm, features or an empty (B, 0), near) of some rows, as the network takes
        them."""
        assert self.mm is not None and self.near is not None
        pts = torch.from_numpy(np.ascontiguousarray(self.points[rows]))
        mm = torch.from_numpy(np.ascontiguousarray(self.mm[rows]))
        feats = (torch.zeros(len(pts), 0) if self.features is None
                 else torch.from_numpy(np.ascontiguousarray(self.features[rows])))
        return pts, mm, feats, torch.from_numpy(np.ascontiguousarray(self.near[rows]))


def nearest_of_pairs(points: npt.NDArray[np.float32], mm: npt.NDArray[np.float64]
                     ) -> npt.NDArray[np.float32]:
    """(N, 2, P) each point's distance to the other part's nearest point, millimetres
    (pykdtree's distances are scipy's cKDTree's, in less than half the time)."""
    from pykdtree.kdtree import KDTree

    out = np.zeros(points.shape[:3], dtype=np.float32)
    for i in range(len(points)):
        a, b = points[i, 0].astype(np.float64), points[i, 1].astype(np.float64)
        out[i, 0] = KDTree(b).query(a, k=1)[0] * mm[i]
        out[i, 1] = KDTree(a).query(b, k=1)[0] * mm[i]
    return out


@dataclass(frozen=True)
class RelationPrediction:
    """Outputs for N pairs; every array (N, 10) in ``Relation`` order."""

    raw_ab: npt.NDArray[np.float32]  # network probabilities for (a, b)
    raw_ba: npt.NDArray[np.float32]  # network probabilities for (b, a)
    decided: npt.NDArray[np.bool_]  # consistent decisions for (a, b)
    confidence: npt.NDArray[np.float64]  # calibrated probability of the decided answer
    probability: npt.NDArray[np.float64]  # calibrated probability that the relation holds
    # (N, ``JOINTS``) the joint head's probabilities, the same for a pair and its swap; None
    # for a network without one
    joint_probability: npt.NDArray[np.float64] | None = None

    def joint(self) -> list[str] | None:
        """The most probable joint of each pair (``JOINTS``), or None without a joint head."""
        if self.joint_probability is None:
            return None
        return [JOINTS[int(k)] for k in self.joint_probability.argmax(1)]


@dataclass
class RelationResult:
    """The outcome of ``train_relations``."""

    model: RelationNet  # best weights, eval mode
    checkpoint: Checkpoint  # best weights, decision, metrics: ship this
    decision: Decision
    history: list[dict[str, float]] = field(default_factory=list)  # one record per evaluation
    losses: list[dict[str, float]] = field(default_factory=list)  # one per step


def training_batch(data: RelationData, cfg: RelationConfig, step: int
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor,
                              torch.Tensor, torch.Tensor]:
    """Step ``step``'s batch: points (B, 2, T, 3), mm (B,), features (B, F), labels (B, 10),
    each drawn point's distance to the other part's whole cloud (B, 2, T), mm, and the joints
    (B,) (-1 where unknown).

    Pairs drawn without replacement (with, when there are fewer than B), ``train_points``
    points per part drawn without replacement, Gaussian jitter of ``jitter_mm`` millimetres,
    and a swap to (b, a) with probability 1/2 when ``swap_augment``.
    """
    rng = np.random.default_rng([cfg.seed, step, 7])
    idx = rng.choice(len(data), cfg.batch_size, replace=len(data) < cfg.batch_size)
    pts, labels = data.points[idx], data.labels[idx]  # (B, 2, P, 3), (B, 10)
    assert data.mm is not None
    mm = data.mm[idx]
    assert data.near is not None
    near = data.near[idx]
    n = pts.shape[2]
    keep = np.argsort(rng.random(pts.shape[:3]), axis=-1)[..., :min(cfg.train_points, n)]
    pts = np.take_along_axis(pts, keep[..., None], axis=2)  # (B, 2, T, 3)
    near = np.take_along_axis(near, keep, axis=2)  # (B, 2, T)
    noise = rng.standard_normal(pts.shape) * (cfg.jitter_mm / mm[:, None, None, None])
    pts = (pts + noise).astype(np.float32)
    feats = (np.zeros((len(idx), 0), np.float32) if data.features is None
             else data.features[idx])
    if cfg.swap_augment:
        from models.geometric import swap_evidence

        flip = rng.random(len(idx)) < 0.5
        pts[flip] = pts[flip][:, ::-1]
        near[flip] = near[flip][:, ::-1]
        labels = np.where(flip[:, None], swap_decision(labels), labels)
        feats[flip] = swap_evidence(feats[flip])
    joints = np.full(len(idx), -1, np.int64) if data.joints is None else data.joints[idx]
    return (torch.from_numpy(np.ascontiguousarray(pts)), torch.from_numpy(mm),
            torch.from_numpy(feats.astype(np.float32)),
            torch.from_numpy(labels.astype(np.float32)),
            torch.from_numpy(np.ascontiguousarray(near, dtype=np.float32)),
            torch.from_numpy(joints))


@torch.no_grad()
def _raw(model: RelationNet, data: RelationData, batch: int
         ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Network probabilities for (a, b) and (b, a), (N, 10) each, in batches."""
    ab, ba, _ = _raw_all(model, data, batch)
    return ab, ba


@torch.no_grad()
def _raw_all(model: RelationNet, data: RelationData, batch: int
             ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32],
                        npt.NDArray[np.float64] | None]:
    """``_raw``'s probabilities and the joint head's (N, ``JOINTS``), or None without one."""
    model.eval()
    outs = []
    for s in range(0, len(data), batch):
        pts, mm, feats, near = data.tensors(slice(s, s + batch))
        outs.append(model.forward_all(pts, mm, feats if model.cfg.pair_features else None,
                                      near))
    if not outs:
        empty = np.zeros((0, len(RELATIONS)), np.float32)
        return empty, empty, None if model.joint_head is None else np.zeros((0, len(JOINTS)))
    ab = torch.sigmoid(torch.cat([o[0] for o in outs])).cpu().numpy()
    ba = torch.sigmoid(torch.cat([o[1] for o in outs])).cpu().numpy()
    joints = None
    if model.joint_head is not None:
        joints = torch.exp(torch.cat([o[2] for o in outs if o[2] is not None])
                           ).double().cpu().numpy()
    return ab, ba, joints


def predict_relations(model_or_checkpoint: RelationNet | Mapping[str, Any] | Path | str,
                      data: RelationData, batch: int = 256,
                      decision: Decision | None = None) -> RelationPrediction:
    """Relations of N ordered pairs, decided consistently with their swaps.

    Args:
        model_or_checkpoint: a ``RelationNet`` (decision from the argument, default
            thresholds 0.5 and temperatures 1), or a checkpoint dict or path (its own decision
            unless given).
        data: the pairs (labels are not read); points in the observer frame, any unit.
        batch: pairs per forward pass.

    Returns:
        A ``RelationPrediction``; ``swap_decision(decided)`` is what the swapped pairs decide.

    Raises:
        ValueError: points of the wrong shape or not finite, or missing pair features.
        CheckpointError: an unusable checkpoint.
    """
    if isinstance(model_or_checkpoint, RelationNet):
        model, own = model_or_checkpoint, Decision.default()
    elif isinstance(model_or_checkpoint, Path | str):
        model, own, _ = load_relation_model(model_or_checkpoint)
    else:
        model, own = relation_model_from_checkpoint(model_or_checkpoint)
    decision = decision or own
    raw_ab, raw_ba, joints = _raw_all(model, data, batch)
    score = combine(raw_ab, raw_ba)
    decided = decide(score, decision.thresholds)
    prob = calibrate(score, decision.temperatures, decision.thresholds)
    return RelationPrediction(raw_ab, raw_ba, decided, np.where(decided, prob, 1 - prob), prob,
                              joints)


def evaluate(model: RelationNet, data: RelationData, batch: int = 256,
             decision: Decision | None = None) -> dict[str, float]:
    """Accuracy (mean over relations) of the decisions and of the raw (a, b) outputs, balanced
    accuracy, mean F1, violation rates of the raw outputs (per entry and per pair) and ECE.
    Without a decision, thresholds are fitted on ``data`` itself (model selection). With a
    joint head and joint labels, also ``joint_metrics``."""
    raw_ab, raw_ba, joint_probs = _raw_all(model, data, batch)
    score = combine(raw_ab, raw_ba)
    truth = data.labels
    if decision is None:
        decision = Decision(np.ones(len(RELATIONS)), fit_thresholds(score, truth))
    decided = decide(score, decision.thresholds)
    prob = calibrate(score, decision.temperatures, decision.thresholds)
    confidence = np.where(decided, prob, 1 - prob)
    hit = decided == truth
    pos, neg = truth.sum(0).clip(min=1), (~truth).sum(0).clip(min=1)
    balanced = ((hit & truth).sum(0) / pos + (hit & ~truth).sum(0) / neg) / 2
    viol = violations(raw_ab, raw_ba)
    f1 = f1_scores(decided, truth)
    out = {"accuracy": float(hit.mean(0).mean()), "balanced_accuracy": float(balanced.mean()),
           "f1": float(f1.mean()), "raw_accuracy": float(((raw_ab > 0.5) == truth).mean()),
           "violation_rate": float(viol.mean()), "pairs_violating": float(viol.any(1).mean()),
           "ece": expected_calibration_error(confidence, hit)}
    if joint_probs is not None and data.joints is not None:
        out.update(joint_metrics(joint_probs, data.joints))
    return out


def joint_metrics(probs: npt.NDArray[np.floating], joints: npt.NDArray[np.int64]
                  ) -> dict[str, float]:
    """The joint head's most probable joints against the labels (-1: unknown, left out):
    accuracy over all labelled pairs, agreement over the pairs that have a joint (the
    nightly's joint agreement) and balanced accuracy (the mean recall of the joints present)."""
    known = joints >= 0
    guess, truth = np.asarray(probs).argmax(1)[known], joints[known]
    if not len(truth):
        return {}
    jointed = truth > 0
    recalls = [float((guess[truth == c] == c).mean()) for c in np.unique(truth)]
    return {"joint_accuracy": float((guess == truth).mean()),
            "joint_agreement": float((guess[jointed] == truth[jointed]).mean())
            if jointed.any() else float("nan"),
            "joint_balanced": float(np.mean(recalls))}


def make_relation_checkpoint(model: RelationNet, decision: Decision, step: int,
                             metrics: Mapping[str, float],
                             data: Mapping[str, Any] | None = None) -> Checkpoint:
    """The self-describing checkpoint of ``model`` (float32 weights, copied)."""
    config = dataclasses.asdict(model.cfg)
    config["widths"] = list(config["widths"])
    return {"format": FORMAT, "method": model.cfg.method, "config": config,
            "state_dict": _state_copy(model, half=False), "precision": "float32",
            "step": int(step), "metrics": {k: float(v) for k, v in metrics.items()},
            "code_version": code_version(), "data": dict(data or {}),
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "temperatures": [float(t) for t in decision.temperatures],
            "thresholds": [float(t) for t in decision.thresholds]}


def relation_model_from_checkpoint(ckpt: Mapping[str, Any], method: str | None = None
                                   ) -> tuple[RelationNet, Decision]:
    """Rebuild the network (eval mode) and its decision from a checkpoint dict.

    Raises:
        CheckpointError: another format or method, missing keys, or weights that do not fit.
    """
    where = str(ckpt.get("created", "<checkpoint>"))
    if ckpt.get("format") != FORMAT:
        raise CheckpointError(where, f"not a {FORMAT} checkpoint")
    if ckpt.get("method") not in learned() or (method and ckpt["method"] != method):
        want = repr(method) if method else " or ".join(map(repr, learned()))
        raise CheckpointError(where, f"method {ckpt.get('method')!r} is not {want}")
    missing = [k for k in (*KEYS, *RELATION_KEYS) if k not in ckpt]
    if missing:
        raise CheckpointError(where, f"missing keys {missing}")
    temps = np.asarray(ckpt["temperatures"], dtype=np.float64)
    thresholds = np.asarray(ckpt.get("thresholds", [0.5] * len(RELATIONS)), dtype=np.float64)
    try:
        cfg = RelationConfig.from_dict(dict(ckpt["config"]))
        if cfg.method != ckpt["method"] or temps.shape != thresholds.shape != (len(RELATIONS),):
            raise ValueError("config method, temperatures or thresholds do not match")
        model = RelationNet(cfg)
        model.load_state_dict({k: v.float() if v.is_floating_point() else v
                               for k, v in ckpt["state_dict"].items()})
    except (ValueError, TypeError, RuntimeError) as exc:
        raise CheckpointError(where, f"does not rebuild a relation network: {exc}") from exc
    return model.eval(), Decision(temps, thresholds)


def save_relation_checkpoint(path: Path | str, ckpt: Mapping[str, Any],
                             half: bool = False) -> Path:
    """Check that ``ckpt`` rebuilds, then write it atomically; returns the path. ``half``
    stores the weights as float16 (halves a shipped file; loading converts them back)."""
    relation_model_from_checkpoint(ckpt)
    if half:
        state = {k: v.half() if v.is_floating_point() else v
                 for k, v in ckpt["state_dict"].items()}
        ckpt = {**ckpt, "state_dict": state, "precision": "float16"}
    return save_checkpoint(ckpt, path)


def load_relation_model(path: Path | str, method: str | None = None
                        ) -> tuple[RelationNet, Decision, Checkpoint]:
    """Read with ``torch.load(weights_only=True)``: (model in eval mode, decision, dict).

    Raises:
        CheckpointError: unreadable, missing keys, another method (or not ``method``).
    """
    ckpt = load_checkpoint(path)
    try:
        model, decision = relation_model_from_checkpoint(ckpt, method)
    except CheckpointError as exc:
        raise CheckpointError(path, exc.reason) from exc
    return model, decision, ckpt


def train_relations(cfg: RelationConfig, train: RelationData, val: RelationData | None = None,
                    progress: Callable[[TrainEvent], None] | None = None,
                    data_info: Mapping[str, Any] | None = None) -> RelationResult:
    """Train ``cfg.method`` for ``cfg.steps`` steps on ``train``, keep the best on ``val``.

    Args:
        cfg: the config; its seed fixes initialisation, batches and augmentation.
        train: labelled pairs. val: pairs for model selection, decision thresholds and
            calibration; when None or empty, the last weights are kept, the thresholds are 0.5
            and the temperatures 1.
        progress: called after every step with a ``TrainEvent`` (``epoch`` set after an
            evaluation).
        data_info: stored as the checkpoint's ``data`` (plain values).

    Returns:
        A ``RelationResult``: best model, its checkpoint with temperatures, history, losses.

    Raises:
        ValueError: no training pairs.
    """
    if not len(train):
        raise ValueError("no training pairs")
    val = val if val is not None and len(val) else None
    info = {"train": len(train), "val": len(val or ()), **(data_info or {})}
    losses: list[dict[str, float]] = []
    history: list[dict[str, float]] = []
    with seeded(cfg.seed):
        model = RelationNet(cfg)
        opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
        best: tuple[float, int, dict[str, torch.Tensor]] | None = None
        clock = time.perf_counter()
        for step in range(cfg.steps):
            losses.append(_step(model, opt, cfg, *training_batch(train, cfg, step)))
            event = TrainEvent(step + 1, cfg.steps, losses[-1])
            if (step + 1) % cfg.eval_every == 0 or step + 1 == cfg.steps:
                record = {"step": float(step + 1), "seconds": time.perf_counter() - clock,
                          **{f"train_{k}": float(np.mean([s[k] for s in
                                                          losses[-cfg.eval_every:]]))
                             for k in losses[-1]}}
                if val is not None:
                    record.update({f"val_{k}": v for k, v in evaluate(model, val).items()})
                history.append(record)
                logger.info("step %d: %s", step + 1,
                            ", ".join(f"{k} {v:.4g}" for k, v in record.items()))
                score = record.get("val_f1", float(step))
                if best is None or score > best[0]:
                    best = (score, step + 1, _state_copy(model, half=False))
                event = dataclasses.replace(event, epoch=record)
            if progress is not None:
                progress(event)
    assert best is not None
    model.load_state_dict(best[2])
    model.eval()
    decision, metrics = Decision.default(), dict(history[-1])
    if val is not None:
        raw_ab, raw_ba = _raw(model, val, 256)
        val_score = combine(raw_ab, raw_ba)
        thresholds = fit_thresholds(val_score, val.labels)
        decision = Decision(fit_temperatures(val_score, val.labels, thresholds), thresholds)
        metrics = {**next(h for h in history if h["step"] == best[1]),
                   **{f"val_{k}_calibrated": v
                      for k, v in evaluate(model, val, decision=decision).items()
                      if k == "ece"}}
    ckpt = make_relation_checkpoint(model, decision, best[1], metrics, info)
    return RelationResult(model, ckpt, decision, history, losses)


# One optimiser step on the six tensors of a batch, as they come from the sampler.
def _step(model: RelationNet, opt: torch.optim.Optimizer, cfg: RelationConfig,  # noqa: PLR0913
          points: torch.Tensor, mm: torch.Tensor, features: torch.Tensor,
          labels: torch.Tensor, near: torch.Tensor, joints: torch.Tensor) -> dict[str, float]:
    """One Adam step on 1 - sat: the losses and satisfactions."""
    model.train()
    logits_ab, logits_ba, log_joints = model.forward_all(
        points, mm, features if cfg.pair_features else None, near)
    t_ab = torch.sigmoid(logits_ab)
    kb = knowledge_base(t_ab, torch.sigmoid(logits_ba), labels, cfg)
    loss = 1 - kb["sat"]
    if log_joints is not None:
        kb["joint"] = joint_knowledge_base(torch.exp(log_joints), joints, t_ab, cfg)
        loss = loss + cfg.joint_weight * (1 - kb["joint"])
    opt.zero_grad(set_to_none=True)
    loss.backward()  # type: ignore[no-untyped-call]
    opt.step()
    return {"loss": loss.item(), **{k: v.item() for k, v in kb.items()}}

