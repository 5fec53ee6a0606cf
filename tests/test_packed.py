"""The GPU training route: the packed corpus reads back bit for bit, and a method trains on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from models.training.packed import pack, unpack


def _corpus(root: Path, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    rows, arrays = [], []
    for i, (views, split, protocol) in enumerate(
            [(1, "train", "observed"), (3, "val", "observed"), (2, "train", "observed"),
             (1, "test", "observed"), (1, "train", "oracle-box")]):
        inputs = rng.random((views, 2, 32, 32, 32)) < 0.2
        target = rng.random((64, 64, 64)) < 0.1
        f = f"examples/{protocol}/ex{i}.npz"
        (root / f).parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(root / f, inputs=inputs, target=target)
        rows.append({"file": f, "status": "ok", "protocol": protocol, "split": split,
                     "part_id": f"p{i}", "category": "fasteners", "kind": "alone",
                     "n_views": views})
        arrays.append((inputs, target))
    pd.DataFrame(rows).to_parquet(root / "index.parquet")
    return arrays


def test_pack_keeps_every_observed_train_and_val_example_bit_for_bit(tmp_path: Path) -> None:
    arrays = _corpus(tmp_path / "corpus", np.random.default_rng(0))
    assert pack(tmp_path / "corpus", tmp_path / "packed", workers=1) == 3
    xs, ys, meta = unpack(tmp_path / "packed")
    assert meta["part_id"] == ["p0", "p1", "p2"] and meta["split"] == ["train", "val", "train"]
    for (x, y), (inputs, target) in zip(zip(xs, ys, strict=True), arrays[:3], strict=True):
        assert x.dtype == bool and np.array_equal(x, inputs) and np.array_equal(y, target)


def test_unpack_refuses_streams_of_other_grids(tmp_path: Path) -> None:
    _corpus(tmp_path / "corpus", np.random.default_rng(1))
    pack(tmp_path / "corpus", tmp_path / "packed", workers=1)
    with pytest.raises(ValueError, match="do not hold 3 examples"):
        unpack(tmp_path / "packed", n_in=16)


def test_a_method_trains_on_a_pack_and_keeps_its_best_checkpoint(tmp_path: Path) -> None:
    import torch

    from models.checkpoint import load_checkpoint
    from models.training.packed import PackedRun, train_packed

    _corpus(tmp_path / "corpus", np.random.default_rng(2))
    pack(tmp_path / "corpus", tmp_path / "packed", workers=1)
    torch.manual_seed(0)
    run = PackedRun("ae", seconds=600, batch=2, eval_every=2, steps=4,
                    overrides={"width": 4})
    path = train_packed(tmp_path / "packed", tmp_path / "out", run, device="cpu")
    ckpt = load_checkpoint(path)
    assert ckpt["method"] == "ae" and ckpt["data"]["train_parts"] == ["p0", "p2"]
    epochs = (tmp_path / "out" / "ae.log").read_text().splitlines()
    assert len(epochs) == 2 and all("val_iou" in e for e in epochs)
