"""The packed corpus that carries training examples to a GPU machine reads back bit for bit."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.packed_corpus import pack, unpack


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
