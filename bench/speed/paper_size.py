"""The paper's network size (64^3 in, 256^3 out) on the machine at hand: weights, training
step time and peak memory of ``gan_lstm`` and ``ae`` at both sizes, on synthetic batches.

The shipped checkpoints are 32^3 in, 64^3 out (CPU-sized); the paper's size is the config
``config_for(method, n_in=64, n_out=256)``. This measures what one training step of it costs
(the critic's updates included for gan_lstm), so a GPU session can size a run before it starts.

    python bench/speed/paper_size.py --batch 8 --views 2 --steps 10

Measured on one NVIDIA H200 (2026-11-27; median of 10 steps after two warm-ups, 2 views):

| size | method | weights | batch | step (s) | examples/s | peak GiB |
|---|---|---|---|---|---|---|
| 32^3 -> 64^3 | gan_lstm | 1,264,681 | 8 | 0.012 | 650 | 0.14 |
| 32^3 -> 64^3 | ae | 379,689 | 8 | 0.005 | 1,663 | 0.12 |
| 64^3 -> 256^3 | gan_lstm | 5,101,870 | 8 | 0.090 | 89 | 5.25 |
| 64^3 -> 256^3 | ae | 1,562,414 | 8 | 0.079 | 101 | 5.16 |
| 64^3 -> 256^3 | gan_lstm | 5,101,870 | 32 | 0.360 | 89 | 21.99 |
| 64^3 -> 256^3 | ae | 1,562,414 | 32 | 0.329 | 97 | 21.83 |

So the paper's size costs about 7x the time per example of the shipped size (gan_lstm), and
fits one GPU at batch 32. The data is the harder part: a 256^3 truth grid is 2 MB as bits, so
the 12k training examples of the shipped checkpoints would be some 24 GB before compression
(the 64^3 pack of ``python -m models.training.packed pack`` is 9 MB). A paper-size run
needs its corpus built on the machine that trains it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from models.data import Batch
from models.train import Learner, config_for

SIZES = {"cpu-default": (32, 64), "paper": (64, 256)}


def synthetic_batch(batch: int, views: int, n_in: int, n_out: int, device: torch.device,
                    seed: int = 0) -> Batch:
    """Random occupancy of a plausible density (views 5% surface, 40% free; truth 20%)."""
    gen = torch.Generator().manual_seed(seed)
    surface = torch.rand(batch, views, 1, n_in, n_in, n_in, generator=gen) < 0.05
    free = torch.rand(batch, views, 1, n_in, n_in, n_in, generator=gen) < 0.4
    target = torch.rand(batch, 1, n_out, n_out, n_out, generator=gen) < 0.2
    inputs = torch.cat([surface, free & ~surface], 2).float()
    return Batch(inputs, None, target.float()).to(device)


def measure(method: str, size: str, batch: int, views: int, steps: int,
            device: torch.device) -> dict[str, object]:
    n_in, n_out = SIZES[size]
    learner = Learner(config_for(method, n_in=n_in, n_out=n_out), device)
    weights = sum(p.numel() for p in learner.model.parameters())
    data = synthetic_batch(batch, views, n_in, n_out, device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    times = []
    for step in range(steps + 2):  # two warm-up steps (kernel choice, allocator)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        learner.step(data, step)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - start)
    steady = sorted(times[2:])
    peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None
    return {"method": method, "size": f"{n_in}^3 -> {n_out}^3", "batch": batch, "views": views,
            "weights": weights, "step_s_median": round(steady[len(steady) // 2], 4),
            "examples_per_s": round(batch / steady[len(steady) // 2], 1),
            "peak_gib": None if peak is None else round(peak, 2),
            "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    ap.add_argument("--methods", nargs="+", default=["gan_lstm", "ae"])
    args = ap.parse_args()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    for size in args.sizes:
        for method in args.methods:
            print(json.dumps(measure(method, size, args.batch, args.views, args.steps, device)),
                  flush=True)


if __name__ == "__main__":
    main()
