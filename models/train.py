"""Training and inference of the learned completion methods: ``gan_lstm``, ``ae`` and ``r2n2``.

``train_completion`` runs a fixed number of steps from a config, seeded throughout (torch,
numpy and python; deterministic algorithms where torch has them): each step's batch and random
draws are pure functions of (seed, step), so resuming from a snapshot repeats exactly the losses
of an uninterrupted run. Every ``eval_every`` steps (an "epoch") it scores validation IoU at
threshold 0.5, keeps the best checkpoint, and hands a resumable snapshot to the progress
callback. ``predict`` turns views into solid probabilities in batches.
"""

from __future__ import annotations

import contextlib
import logging
import random
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from models.baselines import R2N2
from models.checkpoint import (
    Checkpoint,
    Config,
    build_model,
    config_from_dict,
    load_checkpoint,
    make_checkpoint,
    model_from_checkpoint,
    state_copy,
)
from models.completion import (
    CompletionConfig,
    Critic,
    Generator,
    gradient_penalty,
    union_views,
    voxel_loss,
)
from models.data import Batch, CompletionDataset, Example, eval_batches, training_batch
from models.errors import CheckpointError

logger = logging.getLogger(__name__)

Model = Generator | R2N2
Data = CompletionDataset | Sequence[Example]


def config_for(method: str, **overrides: Any) -> Config:
    """The default config of a learned completion method (``models.completions``), with field
    overrides.

    Raises:
        ValueError: unknown method, a method without learning, or an unknown field.
    """
    from cadio.registry import UnknownEntry
    from models.completions import COMPLETIONS

    try:
        spec = COMPLETIONS.get(method)
    except UnknownEntry as exc:
        raise ValueError(str(exc)) from None
    cfg: Config = spec.make_config(**overrides)
    return cfg


@dataclass(frozen=True)
class TrainEvent:
    """What the progress callback sees after each step."""

    step: int  # steps done so far
    steps: int  # steps of the whole run
    losses: dict[str, float]  # this step's losses
    epoch: dict[str, float] | None = None  # the epoch record, when this step ended an epoch
    snapshot: Checkpoint | None = None  # resumable checkpoint at epoch ends: save it to resume


@dataclass
class TrainResult:
    """The outcome of ``train_completion``."""

    model: Model  # the best weights exactly as shipped (rebuilt from ``checkpoint``), eval mode
    checkpoint: Checkpoint  # best validation IoU, float16 weights, no optimiser: ship this
    last: Checkpoint  # the final step, resumable (float32, optimisers, history)
    history: list[dict[str, float]] = field(default_factory=list)  # one record per epoch
    losses: list[dict[str, float]] = field(default_factory=list)  # one per step, from step 0


def iou(logits: Tensor, target: Tensor) -> Tensor:
    """Per-sample IoU of (sigmoid > 0.5) with target > 0.5; 1 where both are empty: (B,)."""
    pred, truth = logits.flatten(1) > 0, target.flatten(1) > 0.5
    inter, union = (pred & truth).sum(1).double(), (pred | truth).sum(1).double()
    return torch.where(union > 0, inter / union.clamp(min=1), 1.0)


@contextlib.contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Seed python, numpy and torch; deterministic torch algorithms inside, restored after."""
    was, was_warn = (torch.are_deterministic_algorithms_enabled(),
                     torch.is_deterministic_algorithms_warn_only_enabled())
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(was, warn_only=was_warn)


def _step_generator(seed: int, step: int) -> torch.Generator:
    """A CPU generator keyed on (seed, step), for the random draws of one step."""
    state = np.random.SeedSequence([seed, step, 2]).generate_state(1)[0]
    return torch.Generator().manual_seed(int(state))


class Learner:
    """The modules and optimisers of one method, with its training step and evaluation."""

    def __init__(self, cfg: Config, device: torch.device) -> None:
        self.cfg, self.device = cfg, device
        self.model = build_model(cfg).to(device)
        self.opt_g = torch.optim.Adam(self.model.parameters(), lr=cfg.lr)
        self.critic: Critic | None = None
        if isinstance(cfg, CompletionConfig) and cfg.gan:
            self.critic = Critic(cfg).to(device)
            # WGAN-GP's Adam betas for the critic: little momentum, as the target moves.
            self.opt_d = torch.optim.Adam(self.critic.parameters(), lr=cfg.lr_d, betas=(0.5, 0.9))

    def step(self, batch: Batch, step: int) -> dict[str, float]:
        """One generator update (after the critic's updates for GAN methods): its losses."""
        self.model.train()
        x = batch.model_input(self.model.input_key)
        observed = union_views(batch.inputs)[:, 0]  # (B, 2, n_in^3) the critic's condition
        logits = self.model(x)  # (B, 1, n_out^3)
        # The critic learns on this very forward pass, detached, then judges it once updated.
        fake = torch.sigmoid(logits).detach()
        losses = self._critic_steps(observed, batch.target, fake, step) if self.critic else {}
        ce = voxel_loss(logits, batch.target, self.cfg.w_occupied, self.cfg.w_empty)
        total = ce
        if self.critic is not None:
            assert isinstance(self.cfg, CompletionConfig)
            self.critic.requires_grad_(False)
            adv = -self.critic(observed, torch.sigmoid(logits)).mean()
            self.critic.requires_grad_(True)
            total = ce + self.cfg.adv_weight * adv
            losses["adv"] = adv.item()
        self.opt_g.zero_grad(set_to_none=True)
        total.backward()
        self.opt_g.step()
        return {"loss": total.item(), "ce": ce.item(), **losses}

    def _critic_steps(self, observed: Tensor, real: Tensor, fake: Tensor,
                      step: int) -> dict[str, float]:
        """WGAN-GP critic updates on this batch: mean D(fake) - D(real) + lambda GP."""
        cfg, critic = self.cfg, self.critic
        assert critic is not None and isinstance(cfg, CompletionConfig)
        gen = _step_generator(cfg.seed, step)
        out: dict[str, float] = {}
        for k in range(cfg.critic_steps):
            gap = critic(observed, real).mean() - critic(observed, fake).mean()
            loss = -gap
            if (step * cfg.critic_steps + k) % cfg.gp_every == 0:
                eps = torch.rand(real.shape[0], generator=gen).to(self.device)
                gp = gradient_penalty(critic, observed, real, fake, eps)
                loss = loss + cfg.gp_lambda * cfg.gp_every * gp
                out["gp"] = gp.item()
            self.opt_d.zero_grad(set_to_none=True)
            loss.backward()
            self.opt_d.step()
        return {"critic": loss.item(), "wasserstein": gap.item(), **out}

    @torch.no_grad()
    def evaluate(self, data: CompletionDataset, counts: Sequence[int]) -> dict[str, float]:
        """Mean IoU (threshold 0.5) and cross-entropy over ``data`` with ``eval_views`` views."""
        self.model.eval()
        ious, ces = [], []
        for indices, views in eval_batches(data, counts, self.cfg.batch_size, self.cfg.eval_views):
            batch = data.batch(indices, views).to(self.device)
            logits = self.model(batch.model_input(self.model.input_key))
            ious.append(iou(logits, batch.target))
            ce = voxel_loss(logits, batch.target, self.cfg.w_occupied, self.cfg.w_empty)
            ces.append(ce.expand(len(indices)))
        return {"val_iou": float(torch.cat(ious).mean()), "val_ce": float(torch.cat(ces).mean())}

    def train_state(self) -> dict[str, Any]:
        """Copies of what a resume needs beside the model weights (float32)."""
        state: dict[str, Any] = {"optim_g": _copy(self.opt_g.state_dict())}
        if self.critic is not None:
            state["critic"] = state_copy(self.critic, half=False)
            state["optim_d"] = _copy(self.opt_d.state_dict())
        return state

    def load(self, ckpt: Mapping[str, Any]) -> None:
        """Restore weights and optimiser states from a resumable snapshot."""
        state = ckpt["train_state"]
        self.model.load_state_dict(ckpt["state_dict"])
        self.opt_g.load_state_dict(state["optim_g"])
        if self.critic is not None:
            self.critic.load_state_dict(state["critic"])
            self.opt_d.load_state_dict(state["optim_d"])


def _copy(value: Any) -> Any:
    """A deep copy of nested containers of tensors (optimiser states), tensors on the CPU."""
    if isinstance(value, Tensor):
        return value.detach().to("cpu", copy=True)
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(_copy(v) for v in value)
    return value


def _mean_losses(window: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """Mean of each loss over the steps that report it (the penalty comes every few steps)."""
    keys = dict.fromkeys(k for s in window for k in s)
    return {f"train_{k}": float(np.mean([s[k] for s in window if k in s])) for k in keys}


class _Run:
    """One training run: steps, epochs, the best checkpoint so far and resumable snapshots."""

    def __init__(self, learner: Learner, train: CompletionDataset,
                 val: CompletionDataset | None, info: dict[str, Any]) -> None:
        self.learner, self.cfg, self.info = learner, learner.cfg, info
        self.train, self.counts = train, train.view_counts()
        self.val, self.val_counts = val, val.view_counts() if val else []
        self.start, self.clock = 0, time.perf_counter()
        self.losses: list[dict[str, float]] = []
        self.history: list[dict[str, float]] = []
        self.best: Checkpoint | None = None

    def restore(self, ckpt: Mapping[str, Any]) -> None:
        self.learner.load(ckpt)
        state = ckpt["train_state"]
        self.start, self.best = int(ckpt["step"]), state["best"]
        self.losses, self.history = list(state["losses"]), list(state["history"])

    def step(self, step: int, steps: int) -> TrainEvent:
        """Train step ``step``; at an epoch's end also validate, keep the best, snapshot."""
        cfg = self.cfg
        batch = training_batch(self.train, self.counts, step, cfg.batch_size, cfg.max_views,
                               cfg.seed, cfg.surface_dropout, cfg.mirror)
        self.losses.append(self.learner.step(batch.to(self.learner.device), step))
        done = step + 1
        event = TrainEvent(done, steps, self.losses[-1])
        if done % cfg.eval_every and done != steps:
            return event
        record = self.epoch(done)
        return replace(event, epoch=record, snapshot=self.snapshot(done))

    def epoch(self, done: int) -> dict[str, float]:
        since = int(self.history[-1]["step"]) if self.history else 0
        record = {"epoch": -(-done // self.cfg.eval_every), "step": done,
                  **_mean_losses(self.losses[since:done]),
                  "seconds": time.perf_counter() - self.clock}
        if self.val is not None:
            record.update(self.learner.evaluate(self.val, self.val_counts))
        self.history.append(record)
        if (self.best is None or self.val is None
                or record["val_iou"] > self.best["metrics"]["val_iou"]):
            self.best = make_checkpoint(self.learner.model, done, record, self.info)
        logger.info("epoch %d: %s", record["epoch"],
                    ", ".join(f"{k} {v:.4g}" for k, v in record.items()))
        return record

    def snapshot(self, done: int) -> Checkpoint:
        """A resumable checkpoint: float32 weights, optimisers, losses, history, best."""
        state = {**self.learner.train_state(), "losses": list(self.losses),
                 "history": list(self.history), "best": self.best}
        metrics = self.history[-1] if self.history else {}
        return make_checkpoint(self.learner.model, done, metrics, self.info, half=False,
                               train_state=state)


def _resume_state(resume: Mapping[str, Any] | Path | str, cfg: Config) -> Checkpoint:
    ckpt = dict(load_checkpoint(resume) if isinstance(resume, Path | str) else resume)
    if "train_state" not in ckpt:
        raise ValueError("checkpoint has no train_state: resume from TrainResult.last or a "
                         "TrainEvent.snapshot, not a shipped checkpoint")
    if config_from_dict(ckpt["method"], ckpt["config"]) != cfg:
        raise ValueError("the checkpoint was trained with another config; resume needs the same")
    return ckpt


def _dataset(data: Data | None, cfg: Config) -> CompletionDataset | None:
    """``data`` as a dataset on the config's grids (None or empty: None)."""
    if data is None or not len(data):
        return None
    data = data if isinstance(data, CompletionDataset) else CompletionDataset(data)
    if (data.n_in, data.n_out) != (cfg.n_in, cfg.n_out):
        raise ValueError(f"data grids {data.n_in} -> {data.n_out} differ from the config's "
                         f"{cfg.n_in} -> {cfg.n_out}")
    return data


# Past the config and the data, each argument is an optional keyword of one run.
def train_completion(cfg: Config, train_data: Data, val_data: Data | None,  # noqa: PLR0913
                     device: torch.device | str = "cpu",
                     steps: int = 1000, progress: Callable[[TrainEvent], None] | None = None,
                     resume: Mapping[str, Any] | Path | str | None = None,
                     data_info: Mapping[str, Any] | None = None,
                     init: Mapping[str, Any] | Path | str | None = None) -> TrainResult:
    """Train one completion method for ``steps`` steps (in total, counting resumed ones).

    Args:
        cfg: ``config_for(method)``, possibly with overrides: the method follows from it.
        train_data, val_data: a ``CompletionDataset`` or a list of ``Example`` on the cfg's
            grids; no validation when val_data is None or empty (the best checkpoint is then
            the last epoch's).
        device: where to train ("cpu", "cuda").
        steps: total generator steps; a resumed run continues from its snapshot's step.
        progress: called after every step with a ``TrainEvent``.
        resume: a resumable snapshot (``TrainResult.last``, ``TrainEvent.snapshot``) or its
            path; the run then repeats exactly the losses of an uninterrupted one.
        data_info: stored as the checkpoints' ``data`` (split sizes, sources); plain values.
        init: a checkpoint (or its path) whose weights start the model, a fine-tune: its
            modules must be the config's (the other fields, such as augmentation, may differ);
            the optimisers and the critic start fresh. Its step and creation time are
            recorded in the checkpoints' ``data`` as ``init``.

    Returns:
        A ``TrainResult``: best model and checkpoint, resumable last checkpoint, history.

    Raises:
        ValueError: no training examples, grids differ from cfg, examples lack the views the
            model reads, a resume snapshot of another config or without training state, an
            init checkpoint whose modules are not the config's, or both resume and init.
    """
    train, val = _dataset(train_data, cfg), _dataset(val_data, cfg)
    if train is None:
        raise ValueError("no training examples")
    if resume is not None and init is not None:
        raise ValueError("resume continues a run and init starts one: give one of them")
    start = None if init is None else dict(
        load_checkpoint(init) if isinstance(init, Path | str) else init)
    info = _data_info(train, val, data_info, start)
    with seeded(cfg.seed):
        run = _Run(Learner(cfg, torch.device(device)), train, val, info)
        if resume is not None:
            run.restore(_resume_state(resume, cfg))
        if start is not None:
            try:
                run.learner.model.load_state_dict(model_from_checkpoint(start).state_dict())
            except (CheckpointError, RuntimeError) as exc:
                raise ValueError(f"the init checkpoint does not fit {cfg.method}: {exc}") from exc
            if run.val:  # where the fine-tune starts, on its own validation split
                info["init"].update(run.learner.evaluate(run.val, run.val_counts))
        for step in range(run.start, steps):
            event = run.step(step, steps)
            if progress is not None:
                progress(event)
        last = run.snapshot(max(run.start, steps))
    best = run.best or make_checkpoint(run.learner.model, last["step"], {}, info)
    model = model_from_checkpoint(best).to(device)
    return TrainResult(model, best, last, run.history, run.losses)


def _data_info(train: CompletionDataset, val: CompletionDataset | None,
               data_info: Mapping[str, Any] | None, start: Mapping[str, Any] | None
               ) -> dict[str, Any]:
    """The checkpoints' ``data``: split sizes, the caller's ``data_info`` and, for a fine-tune,
    its init checkpoint and the parts that one learned from."""
    info = {"train": len(train), "val": len(val or ()), **(data_info or {})}
    if start is not None:
        info["init"] = {"method": start.get("method"), "step": start.get("step"),
                        "created": start.get("created")}
        # The weights learned from the init's parts too: a held-out figure must leave them out.
        before = start.get("data", {}).get("train_parts", [])
        if before or "train_parts" in info:
            info["train_parts"] = sorted({*before, *info.get("train_parts", [])})
    return info


@torch.no_grad()
def predict(model: Model, data: CompletionDataset | Sequence[np.ndarray] | np.ndarray,
            batch_size: int = 8, n_views: int | None = None) -> np.ndarray:
    """Probabilities of solid for each example, computed in batches on the model's device.

    Args:
        model: a ``Generator`` (reads occupancy views) or ``R2N2`` (reads depth views).
        data: a ``CompletionDataset`` (the field the model reads, first ``n_views`` views,
            default all), or per-example arrays of that field, (V_i, ...) each, or one stacked
            (N, V, ...) array. Examples with different V are batched apart.
        batch_size: examples per forward pass.

    Returns:
        (N, n_out, n_out, n_out) float32 in [0, 1], in the order of ``data``.

    Raises:
        ValueError: arrays of the wrong shape for the model (the message names the shape).
    """
    model.eval()
    device = next(model.parameters()).device
    if isinstance(data, CompletionDataset):
        fields = [getattr(data.example(i), model.input_key) for i in range(len(data))]
        if any(f is None for f in fields):
            raise ValueError(f"the examples carry no {model.input_key!r} views, which "
                             f"{type(model).__name__} reads")
        items = [f[:n_views] for f in fields]
    else:
        items = [np.asarray(x)[:n_views] for x in data]
    m = model.cfg.n_out
    out = np.empty((len(items), m, m, m), dtype=np.float32)
    by_v: dict[int, list[int]] = {}
    for i, x in enumerate(items):
        by_v.setdefault(len(x), []).append(i)
    for idx in by_v.values():
        for s in range(0, len(idx), batch_size):
            chunk = idx[s:s + batch_size]
            x = torch.from_numpy(np.stack([items[i] for i in chunk])).to(device)
            out[chunk] = torch.sigmoid(model(x))[:, 0].float().cpu().numpy()
    return out


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
