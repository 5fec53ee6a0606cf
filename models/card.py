"""The model card of a folder of completion checkpoints: what they are, learned from, and score.

Written beside the shipped checkpoints (``MODEL_CARD.md``) by ``mateqa train completion``:
the data (sources, parts and examples per split and category), each checkpoint (method,
protocol, size, steps, best validation IoU, code version), the held-out scores of every method
in both protocols beside the paper, and the exact command that made them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from models.checkpoint import load_checkpoint
from reports.completion import paper_iou_table
from reports.tables import markdown_table


def checkpoint_table(folder: Path) -> pd.DataFrame:
    """One row per checkpoint of ``folder``: method, protocol, weights, size, step, IoU."""
    rows = []
    for path in sorted(folder.glob("*.pt")):
        ckpt = load_checkpoint(path)
        data = ckpt["data"]
        rows.append({
            "file": path.name, "method": ckpt["method"], "protocol": data.get("protocol", ""),
            "weights": sum(v.numel() for v in ckpt["state_dict"].values()),
            "MB": round(path.stat().st_size / 1e6, 2), "step": ckpt["step"],
            "val_iou": round(float(ckpt["metrics"].get("val_iou", float("nan"))), 4),
            "train_parts": len(data.get("train_parts", [])),
            "train_examples": data.get("train_examples", 0), "code": ckpt["code_version"]})
    return pd.DataFrame(rows)


def model_card(folder: Path, data: pd.DataFrame, categories: pd.DataFrame,
               command: str, notes: Sequence[str] = (),
               config: Mapping[str, Any] | None = None) -> str:
    """The card's Markdown.

    Args:
        data: parts and examples per split and category of the training dataset.
        categories: ``completion_categories.csv`` of the held-out evaluation.
        command: the exact command that trained the checkpoints.
        notes: free sentences (hardware, time taken).
        config: the training knobs beyond each checkpoint's own config (steps, threads).
    """
    lines = ["# Completion checkpoints", "",
             "Shape completion from single RGB-D views (and sequences of views): `gan_lstm` "
             "(3D conv encoder-decoder with skips, a 3D conv-LSTM over the views, conditional "
             "WGAN-GP critic), and the learned baselines `ae` (the same generator without LSTM "
             "and critic) and `r2n2` (3D-R2N2 on depth views of the seen surface only, without "
             "the seen-free and unknown states the others read: labelled surface-only, no fair "
             "baseline). One checkpoint per method and "
             "protocol; the nightly loads them with `torch.load(weights_only=True)`.", "",
             "## Checkpoints", "", markdown_table(checkpoint_table(folder)), "",
             "## Data", "", "Parts are split by part (never by view); the nightly's own sample "
             "parts are never trained on.", "", markdown_table(data), ""]
    for protocol in ("observed", "oracle-box"):
        rows = categories[categories["protocol"] == protocol]
        if len(rows):
            lines += [f"## Held-out IoU, one view (protocol: {protocol})", "",
                      markdown_table(paper_iou_table(rows).round(2)), ""]
    if config:
        lines += ["## Training", "", ", ".join(f"{k} {v}" for k, v in config.items()), ""]
    lines += [*notes, "", "Trained with:", "", f"    {command}", ""]
    return "\n".join(lines)
