"""The GPU training route: a corpus packed small enough to travel, and training on it.

The training workspace keeps one compressed ``.npz`` shard per example (about 700 MB for 24k
examples, most of it depth views that only ``r2n2`` reads). ``pack`` keeps the observed train
and val examples' seen-surface and seen-free input grids and their truth grids as bits, each
stream lzma-compressed (about 13 MB for 17k examples), with the view count and the split, part
and category of each; ``unpack`` reads them back bit for bit. ``train`` trains one method on a
pack with ``models.train.train_completion`` itself, so the checkpoint is the one the train flow
would ship; only the batch, the epoch length and a wall-clock budget are chosen here, and at
every epoch the best checkpoint so far is written, so a run stopped by its budget keeps its best.

    python -m models.training.packed pack train-workspace/datasets/corpus gpu/data
    python -m models.training.packed train gpu/data OUT_DIR gan_lstm --seconds 420 --batch 32

METHOD: gan_lstm, ae, or lstm (gan_lstm without its critic, the critic's ablation).
``--width``, ``--mirror`` and ``--adv-weight`` override the config's fields; ``--tag`` names
the checkpoint and log apart when several runs of one method share OUT_DIR.
"""

from __future__ import annotations

import argparse
import json
import logging
import lzma
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd

from models.checkpoint import Config, save_checkpoint
from models.data import CompletionDataset
from models.train import TrainEvent, config_for, train_completion

log = logging.getLogger(__name__)

COLUMNS = ("part_id", "category", "split", "kind", "n_views")


Bits = npt.NDArray[np.uint8]
Grids = list[npt.NDArray[np.bool_]]


def _read(path: Path) -> tuple[int, Bits, Bits]:
    with np.load(path, allow_pickle=False) as z:
        inputs, target = z["inputs"], z["target"]
    return inputs.shape[0], np.packbits(inputs.reshape(-1)), np.packbits(target.reshape(-1))


def pack(corpus: Path, out: Path, splits: tuple[str, ...] = ("train", "val"),
         workers: int = 2) -> int:
    """Pack the observed examples of ``splits`` listed ok in ``corpus/index.parquet`` into
    ``out``; returns how many."""
    index = pd.read_parquet(corpus / "index.parquet")
    index = index[(index["status"] == "ok") & (index["protocol"] == "observed")
                  & index["split"].isin(splits)].reset_index(drop=True)
    if not len(index):
        raise ValueError(f"{corpus}: no observed examples in splits {splits}")
    with ProcessPoolExecutor(workers) as pool:
        read = list(pool.map(_read, [corpus / f for f in index["file"]], chunksize=64))
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "views.npy", np.array([r[0] for r in read], np.int8))
    for name, k in (("inputs", 1), ("target", 2)):
        stream = np.concatenate([r[k] for r in read]).tobytes()
        (out / f"{name}.xz").write_bytes(lzma.compress(stream, preset=6))
    meta = {c: [v.item() if hasattr(v, "item") else v for v in index[c]] for c in COLUMNS}
    (out / "meta.json").write_text(json.dumps(meta))
    return len(index)


def unpack(packed: Path, n_in: int = 32, n_out: int = 64
           ) -> tuple[Grids, Grids, dict[str, list[Any]]]:
    """The packed examples: inputs (V, 2, n_in^3) bool, targets (n_out^3) bool, and meta."""
    views = np.load(packed / "views.npy").astype(int)
    meta = json.loads((packed / "meta.json").read_text())
    inputs = np.frombuffer(lzma.decompress((packed / "inputs.xz").read_bytes()), np.uint8)
    target = np.frombuffer(lzma.decompress((packed / "target.xz").read_bytes()), np.uint8)
    per_view, per_target = 2 * n_in ** 3 // 8, n_out ** 3 // 8
    if inputs.size != views.sum() * per_view or target.size != len(views) * per_target:
        raise ValueError(f"{packed}: streams do not hold {len(views)} examples of "
                         f"{n_in}^3 -> {n_out}^3 grids")
    starts = np.concatenate([[0], np.cumsum(views * per_view)])
    xs, ys = [], []
    for i, v in enumerate(views):
        x = np.unpackbits(inputs[starts[i]:starts[i + 1]]).astype(bool)
        xs.append(x.reshape(v, 2, n_in, n_in, n_in))
        y = np.unpackbits(target[i * per_target:(i + 1) * per_target]).astype(bool)
        ys.append(y.reshape(n_out, n_out, n_out))
    return xs, ys, meta


class Budget(Exception):
    """The wall-clock budget is spent: the best checkpoint is already on disk."""


def datasets(packed: Path) -> tuple[CompletionDataset, CompletionDataset, dict[str, Any]]:
    """The packed corpus as train and val datasets, and its meta."""
    xs, ys, meta = unpack(packed)
    split = {name: [i for i, s in enumerate(meta["split"]) if s == name]
             for name in ("train", "val")}
    train, val = (CompletionDataset.from_arrays([xs[i] for i in idx], [ys[i] for i in idx])
                  for idx in split.values())
    return train, val, meta


@dataclass(frozen=True)
class PackedRun:
    """How one method trains on a pack. method: gan_lstm, ae, or lstm (gan_lstm without its
    critic). seconds: the wall-clock budget. overrides: fields of the method's config
    (``width``, ``mirror``, ``adv_weight``); tag: a suffix naming the checkpoint and log apart;
    init: a checkpoint whose weights start the run (a fine-tune)."""

    method: str
    seconds: float = 420.0
    batch: int = 32
    eval_every: int = 250
    lr: float = 1e-3
    lr_d: float = 1e-4
    steps: int = 100_000
    overrides: dict[str, float] = field(default_factory=dict)
    tag: str = ""
    init: Path | None = None

    def config(self) -> Config:
        base = "gan_lstm" if self.method == "lstm" else self.method
        chosen: dict[str, Any] = {"batch_size": self.batch, "eval_every": self.eval_every,
                                  "lr": self.lr, **self.overrides}
        if self.method == "gan_lstm":
            chosen["lr_d"] = self.lr_d
        if self.method == "lstm":
            chosen["gan"] = False
        return config_for(base, **chosen)


def train_packed(packed: Path, out: Path, run: PackedRun, device: str | None = None) -> Path:
    """Train ``run.method`` on a pack until its budget is spent; the best checkpoint so far is
    written at every epoch (``out/completion-<method><tag>-observed.pt``), each epoch's
    figures to ``out/<method><tag>.log``. Returns the checkpoint's path."""
    import torch

    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    clock = time.perf_counter()
    train, val, meta = datasets(packed)
    log.info("%s: %d train, %d val examples in %.0f s on %s", run.method, len(train), len(val),
             time.perf_counter() - clock, device)
    cfg = run.config()
    parts = sorted({p for p, s in zip(meta["part_id"], meta["split"], strict=True)
                    if s == "train"})
    info = {"protocol": "observed", "train_parts": parts, "train_examples": len(train),
            "val_examples": len(val), "dataset": "datasets/corpus (packed)",
            "device": torch.cuda.get_device_name() if device == "cuda" else "cpu",
            "seconds": run.seconds}
    out.mkdir(parents=True, exist_ok=True)
    name = f"{cfg.method}{run.tag}"
    path = out / f"completion-{name}-observed.pt"
    start = time.perf_counter()
    with (out / f"{name}.log").open("w") as epochs:
        def progress(event: TrainEvent) -> None:
            if event.epoch is None:
                return
            epochs.write(json.dumps(event.epoch) + "\n")
            epochs.flush()
            log.info("%s %s", name, json.dumps({k: round(v, 4) for k, v in event.epoch.items()}))
            best = event.snapshot["train_state"]["best"] if event.snapshot else None
            if best is not None and int(best["step"]) == event.step:
                save_checkpoint(best, path)
            if time.perf_counter() - start > run.seconds:
                raise Budget

        try:
            train_completion(cfg, train, val, device=device, steps=run.steps,
                             progress=progress, data_info=info, init=run.init)
        except Budget:
            pass
    log.info("%s: done in %.0f s", name, time.perf_counter() - clock)
    return path


def main(argv: list[str] | None = None) -> int:
    """``pack CORPUS OUT`` or ``train PACK OUT METHOD [options]`` (the module's docstring)."""
    ap = argparse.ArgumentParser(prog="python -m models.training.packed",
                                 description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pack", help="pack a corpus's observed train and val examples")
    p.add_argument("corpus", type=Path, help="a corpus folder (index.parquet, examples/)")
    p.add_argument("out", type=Path)
    t = sub.add_parser("train", help="train one method on a pack within a wall-clock budget")
    t.add_argument("pack", type=Path)
    t.add_argument("out", type=Path)
    t.add_argument("method", choices=["gan_lstm", "ae", "lstm"])
    defaults = PackedRun("gan_lstm")
    for name in ("seconds", "lr", "lr_d"):
        t.add_argument(f"--{name.replace('_', '-')}", type=float, default=getattr(defaults, name))
    for name in ("batch", "eval_every", "steps"):
        t.add_argument(f"--{name.replace('_', '-')}", type=int, default=getattr(defaults, name))
    for name in ("width", "mirror", "adv_weight"):
        t.add_argument(f"--{name.replace('_', '-')}", type=float, default=None)
    t.add_argument("--tag", default="", help="suffix of the checkpoint and log names")
    t.add_argument("--init", type=Path, default=None,
                   help="a checkpoint whose weights start the run (a fine-tune)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
    if args.command == "pack":
        log.info("packed %d examples into %s", pack(args.corpus, args.out), args.out)
        return 0
    import torch

    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.set_num_threads(4)
    torch.backends.cudnn.benchmark = True  # fixed shapes per view count: pick the fastest kernels
    overrides = {k: float(getattr(args, k)) for k in ("width", "mirror", "adv_weight")
                 if getattr(args, k) is not None}
    if "width" in overrides:
        overrides["width"] = int(overrides["width"])
    run = PackedRun(args.method, args.seconds, args.batch, args.eval_every, args.lr, args.lr_d,
                    args.steps, overrides, args.tag, args.init)
    train_packed(args.pack, args.out, run)
    return 0


if __name__ == "__main__":
    sys.exit(main())
