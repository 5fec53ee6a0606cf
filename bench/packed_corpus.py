"""A corpus's observed train and val examples, packed small enough to travel to a GPU machine.

The training workspace keeps one compressed ``.npz`` shard per example (about 700 MB for 24k
examples, most of it depth views that only ``r2n2`` reads). Packed here: the seen-surface and
seen-free input grids and the truth grids as bits, each stream lzma-compressed (about 13 MB for
the 17k train and val examples), with the view count and the split, part and category of each.
``bench/train_packed.py`` trains on it.

    python bench/packed_corpus.py train-workspace/datasets/corpus gpu/data
"""

from __future__ import annotations

import argparse
import json
import lzma
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

COLUMNS = ("part_id", "category", "split", "kind", "n_views")


def _read(path: Path) -> tuple[int, np.ndarray, np.ndarray]:
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
           ) -> tuple[list[np.ndarray], list[np.ndarray], dict[str, list]]:
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("corpus", type=Path, help="a corpus folder (index.parquet, examples/)")
    ap.add_argument("out", type=Path)
    args = ap.parse_args()
    print(f"packed {pack(args.corpus, args.out)} examples into {args.out}")


if __name__ == "__main__":
    main()
