"""Benchmark of the completion models: training and inference throughput, peak memory.

For each method (gan_lstm, ae, r2n2) and each size, ``cpu`` (the default configs, 32^3 in,
64^3 out, training batch 8) and ``paper`` (64^3 in, 256^3 out, batch 1), in a fresh process
each so a case's peak memory is its own: training steps per second (the real training step,
critic and penalty included, on sequences of 1-3 views sampled as in training), inference parts
per second with ``predict`` (one view), the process's peak resident memory and what the case
added to it, and on CUDA torch's peak allocated memory. Synthetic boxes and cylinders stand in
for parts: speed does not depend on what the grids hold. Runs in a few minutes on 2 cores.

Usage: ``PYTHONPATH=$PWD .venv/bin/python bench/speed/completion.py [--steps 5] [--threads N]
[--sizes cpu paper] [--device cpu]``
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run from anywhere

import torch

from models.data import CompletionDataset, training_batch
from models.synthetic import synthetic_examples
from models.train import Learner, config_for, count_parameters, predict

METHODS = ("gan_lstm", "ae", "r2n2")
SIZES = {  # name: (grid overrides, training batch, parts to predict)
    "cpu": ({}, 8, 16),
    "paper": ({"n_in": 64, "n_out": 256}, 1, 2),
}


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_case(method: str, size: str, steps: int, threads: int, device: str) -> dict[str, object]:
    """Time ``steps`` training steps (after one warm-up) and prediction of a few parts."""
    torch.set_num_threads(threads)
    grids, batch, n_parts = SIZES[size]
    cfg = config_for(method, batch_size=batch, **grids)
    data = CompletionDataset(synthetic_examples(max(batch, n_parts), cfg.n_in, cfg.n_out, 3))
    counts = data.view_counts()
    start_mb = _peak_mb()
    learner = Learner(cfg, torch.device(device))
    for step in range(steps + 1):
        if step == 1:
            t0 = time.perf_counter()
        learner.step(training_batch(data, counts, step, batch, cfg.max_views, 0).to(device), step)
    train_s = (time.perf_counter() - t0) / steps
    predict(learner.model, data, batch_size=batch, n_views=1)  # warm-up
    t0 = time.perf_counter()
    predict(learner.model, data, batch_size=batch, n_views=1)
    infer = len(data) / (time.perf_counter() - t0)
    cuda = torch.cuda.max_memory_allocated() / 2**20 if device.startswith("cuda") else None
    return {"method": method, "size": f"{size} {cfg.n_in}->{cfg.n_out}", "batch": batch,
            "params": count_parameters(learner.model), "steps/s": 1 / train_s,
            "s/step": train_s, "parts/s": infer, "peak RSS MB": _peak_mb(),
            "added MB": _peak_mb() - start_mb, "torch MB": cuda}


def _child(queue: mp.Queue, *args: object) -> None:  # type: ignore[type-arg]
    try:
        queue.put(run_case(*args))  # type: ignore[arg-type]
    except (RuntimeError, MemoryError) as exc:
        queue.put({"method": args[0], "size": args[1], "error": str(exc)[:80]})


def isolated(*args: object) -> dict[str, object]:
    """``run_case`` in a fresh process, so peak memory is the case's own."""
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_child, args=(queue, *args))
    proc.start()
    proc.join()
    if proc.exitcode != 0:
        return {"method": args[0], "size": args[1], "error": f"exit code {proc.exitcode}"}
    return dict(queue.get())


def table(rows: list[dict[str, object]]) -> str:
    cols = ["method", "size", "batch", "params", "steps/s", "s/step", "parts/s",
            "peak RSS MB", "added MB", "torch MB", "error"]
    cols = [c for c in cols if any(c in r for r in rows)]

    def cell(v: object) -> str:
        if v is None:
            return "n/a"
        if isinstance(v, float):
            return f"{v:.0f}" if v >= 100 else f"{v:.3g}"
        return str(v)

    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    out += ["| " + " | ".join(cell(r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=5, help="timed training steps per case")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--sizes", nargs="+", choices=list(SIZES), default=list(SIZES))
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    rows = [isolated(m, s, args.steps if s == "cpu" else 1, args.threads, args.device)
            for s in args.sizes for m in METHODS]
    print(f"torch {torch.__version__}, {args.threads} threads, device {args.device}")
    print(table(rows))


if __name__ == "__main__":
    main()
