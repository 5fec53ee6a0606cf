"""Train a completion method on a corpus packed by ``bench/packed_corpus.py``, on a GPU.

The packed corpus (bit-packed, lzma-compressed observed inputs and truth grids of the train and
val splits, about 13 MB for 17k examples) travels where the workspace's 700 MB of shards cannot.
Training is ``models.train.train_completion`` itself, so the checkpoint is the one the flow
would ship; only the batch, the epoch length and a wall-clock budget are chosen here. At every
epoch the best checkpoint so far is written, so a run stopped by its budget keeps its best.

    python bench/train_packed.py PACK OUT_DIR METHOD --seconds 420 --batch 32

METHOD: gan_lstm, ae, or lstm (gan_lstm without its critic, the critic's ablation).
``--width``, ``--mirror`` and ``--adv-weight`` override the config's fields; ``--tag`` names
the checkpoint and log apart when several runs of one method share OUT_DIR.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.packed_corpus import unpack
from models.checkpoint import save_checkpoint
from models.data import CompletionDataset
from models.train import config_for, train_completion


class Budget(Exception):
    """The wall-clock budget is spent: the best checkpoint is already on disk."""


def datasets(packed: Path) -> tuple[CompletionDataset, CompletionDataset, dict]:
    """The packed corpus as train and val datasets, and its meta."""
    xs, ys, meta = unpack(packed)
    split = {name: [i for i, s in enumerate(meta["split"]) if s == name]
             for name in ("train", "val")}
    train, val = (CompletionDataset.from_arrays([xs[i] for i in idx], [ys[i] for i in idx])
                  for idx in split.values())
    return train, val, meta


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("pack", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("method", choices=["gan_lstm", "ae", "lstm"])
    ap.add_argument("--seconds", type=float, default=420)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--eval-every", type=int, default=250)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--lr-d", type=float, default=1e-4)
    ap.add_argument("--steps", type=int, default=100_000)
    ap.add_argument("--width", type=int, default=None)
    ap.add_argument("--mirror", type=float, default=None)
    ap.add_argument("--adv-weight", type=float, default=None)
    ap.add_argument("--tag", default="", help="suffix of the checkpoint and log names")
    ap.add_argument("--init", type=Path, default=None,
                    help="a checkpoint whose weights start the run (a fine-tune)")
    args = ap.parse_args()
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.set_num_threads(4)
    torch.backends.cudnn.benchmark = True  # fixed shapes per view count: pick the fastest kernels
    device = "cuda" if torch.cuda.is_available() else "cpu"
    clock = time.perf_counter()
    train, val, meta = datasets(args.pack)
    print(f"{args.method}: {len(train)} train, {len(val)} val examples in "
          f"{time.perf_counter() - clock:.0f} s on {device}", flush=True)
    base = "gan_lstm" if args.method == "lstm" else args.method
    overrides = {"batch_size": args.batch, "eval_every": args.eval_every, "lr": args.lr}
    if args.method == "gan_lstm":
        overrides["lr_d"] = args.lr_d
    if args.method == "lstm":
        overrides["gan"] = False
    for field in ("width", "mirror", "adv_weight"):
        if getattr(args, field) is not None:
            overrides[field] = getattr(args, field)
    cfg = config_for(base, **overrides)
    parts = sorted({p for p, s in zip(meta["part_id"], meta["split"], strict=True) if s == "train"})
    device_name = torch.cuda.get_device_name() if device == "cuda" else "cpu"
    info = {"protocol": "observed", "train_parts": parts, "train_examples": len(train),
            "val_examples": len(val), "dataset": "datasets/corpus (packed)", "device": device_name,
            "seconds": args.seconds}
    args.out.mkdir(parents=True, exist_ok=True)
    name = f"{cfg.method}{args.tag}"
    path = args.out / f"completion-{name}-observed.pt"
    start = time.perf_counter()
    log = (args.out / f"{name}.log").open("w")

    def progress(event) -> None:  # type: ignore[no-untyped-def]
        if event.epoch is None:
            return
        print(json.dumps(event.epoch), file=log, flush=True)
        print(name, json.dumps({k: round(v, 4) for k, v in event.epoch.items()}), flush=True)
        best = event.snapshot["train_state"]["best"]
        if best is not None and int(best["step"]) == event.step:
            save_checkpoint(best, path)
        if time.perf_counter() - start > args.seconds:
            raise Budget

    with log:
        try:
            train_completion(cfg, train, val, device=device, steps=args.steps,
                             progress=progress, data_info=info, init=args.init)
        except Budget:
            pass
    print(f"{name}: done in {time.perf_counter() - clock:.0f} s", flush=True)


if __name__ == "__main__":
    main()
