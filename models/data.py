"""Training examples for shape completion: the data pipeline's contract, shards and batches.

One example is one part seen from a sequence of V (1..8) views, all in one cubic grid placed
from the observed points and the camera; the truth is voxelized into the same grid. Examples
come from lists of arrays or from ``.npz`` shards (one example each, keys ``inputs``, ``depth``,
``target``, ``meta``), which are read lazily so a large set never sits in memory at once.

Batches are drawn as pure functions of (seed, step): which examples, how many views and which
ones. So a resumed run sees exactly the batches an uninterrupted one would, with no sampler
state to save.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor
from torch.utils.data import Dataset

from cadio.workspace import create_beside
from models.errors import ShardError

MAX_VIEWS = 8  # the contract's upper bound on V
STATES = 2  # channels of a view's input grid: seen surface, seen free
SHARD_KEYS = ("inputs", "depth", "target", "meta")


@dataclass(frozen=True, eq=False)
class Example:
    """One part from V views in one grid (x right, y away from the first camera, z up).

    inputs: (V, 2, n_in, n_in, n_in) bool, each view's seen-surface and seen-free voxels (a
        voxel in neither is unknown).
    depth: (V, 2, 2 n_in, 2 n_in) float32 or None: channel 0 the distance along +y of the
        nearest observed point of each (x, z) cell over the grid side (1 where none), channel 1
        the observed mask. Only the ``r2n2`` baseline reads it.
    target: (n_out, n_out, n_out) bool, the part's solid.
    meta: the pipeline's metadata (part_id, category, split, azimuths, grid_to_world, ...).

    Raises:
        ValueError: an array breaks these shapes; the message names the shape found.
    """

    inputs: npt.NDArray[np.bool_]
    target: npt.NDArray[np.bool_]
    depth: npt.NDArray[np.float32] | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        inputs, target = np.asarray(self.inputs), np.asarray(self.target)
        shape = inputs.shape
        if (inputs.ndim != 5 or not 1 <= shape[0] <= MAX_VIEWS or shape[1] != STATES
                or len(set(shape[2:])) != 1):
            raise ValueError(f"inputs must be (V <= {MAX_VIEWS}, {STATES}, n, n, n); got {shape}")
        if target.ndim != 3 or len(set(target.shape)) != 1:
            raise ValueError(f"target must be (n_out, n_out, n_out); got {target.shape}")
        object.__setattr__(self, "inputs", inputs.astype(bool, copy=False))
        object.__setattr__(self, "target", target.astype(bool, copy=False))
        if self.depth is not None:
            d = 2 * shape[2]
            depth = np.asarray(self.depth, dtype=np.float32)
            if depth.shape != (shape[0], 2, d, d):
                raise ValueError(f"depth must be ({shape[0]}, 2, {d}, {d}); got {depth.shape}")
            object.__setattr__(self, "depth", depth)

    @property
    def n_views(self) -> int:
        return int(self.inputs.shape[0])


def read_shard(path: Path | str) -> Example:
    """One example from an ``.npz`` shard written by the data pipeline.

    Other keys (the pipeline's baselines and observed points) are not read.

    Raises:
        ShardError: unreadable, lacking one of ``SHARD_KEYS``, bad meta JSON or bad shapes.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = sorted(set(SHARD_KEYS) - set(z.files))
            if missing:
                raise ShardError(path, f"keys {sorted(z.files)} lack {missing}")
            arrays = {k: z[k] for k in SHARD_KEYS}
        meta = json.loads(arrays.pop("meta").item())
        return Example(arrays["inputs"], arrays["target"], arrays["depth"], meta)
    except (OSError, ValueError) as exc:
        raise ShardError(path, str(exc)) from exc


def write_shard(path: Path | str, example: Example) -> None:
    """Write ``example`` as a compressed shard, atomically (temp file + rename)."""
    if example.depth is None:
        raise ValueError("a shard needs the depth views")
    path = Path(path)
    fd, tmp = create_beside(path, ".npz")
    with os.fdopen(fd, "wb") as f:
        np.savez_compressed(f, inputs=example.inputs, depth=example.depth,
                            target=example.target, meta=np.array(json.dumps(example.meta)))
    os.replace(tmp, path)


@dataclass(frozen=True)
class Batch:
    """Stacked examples with a common view count V, as float32 tensors."""

    inputs: Tensor  # (B, V, 2, n_in, n_in, n_in) seen surface, seen free
    depth: Tensor | None  # (B, V, 2, 2 n_in, 2 n_in)
    target: Tensor  # (B, 1, n_out, n_out, n_out) 1 = solid

    def to(self, device: torch.device | str) -> Batch:
        depth = None if self.depth is None else self.depth.to(device)
        return Batch(self.inputs.to(device), depth, self.target.to(device))

    def model_input(self, key: str) -> Tensor:
        """The field a model reads (its ``input_key``: ``inputs`` or ``depth``)."""
        x = getattr(self, key)
        if x is None:
            raise ValueError(f"the examples carry no {key!r} views, which this model reads")
        return x


class CompletionDataset(Dataset[dict[str, Tensor]]):
    """Examples in memory or as shard paths (read on access); all share n_in and n_out."""

    def __init__(self, examples: Sequence[Example] = (), paths: Sequence[Path | str] = ()) -> None:
        if bool(examples) == bool(paths):
            raise ValueError("give examples or shard paths, not both or neither")
        self._examples = list(examples)
        self._paths = [Path(p) for p in paths]
        first = self._examples[0] if self._examples else read_shard(self._paths[0])
        self.n_in, self.n_out = first.inputs.shape[2], first.target.shape[0]
        for ex in self._examples:
            self._check(ex)

    @classmethod
    def from_arrays(cls, inputs: Sequence[np.ndarray], target: Sequence[np.ndarray],
                    depth: Sequence[np.ndarray] | None = None,
                    meta: Sequence[dict[str, Any]] | None = None) -> CompletionDataset:
        """Parallel lists of per-example arrays (shapes as in ``Example``)."""
        n = len(inputs)
        if len(target) != n or (depth is not None and len(depth) != n):
            raise ValueError("inputs, target and depth must list the same number of examples")
        depths = list(depth) if depth is not None else [None] * n
        metas = list(meta) if meta is not None else [{} for _ in range(n)]
        return cls([Example(*args) for args in zip(inputs, target, depths, metas, strict=True)])

    @classmethod
    def from_shards(cls, paths: Sequence[Path | str]) -> CompletionDataset:
        return cls(paths=paths)

    def _check(self, ex: Example) -> Example:
        if (ex.inputs.shape[2], ex.target.shape[0]) != (self.n_in, self.n_out):
            raise ValueError(f"example grids {ex.inputs.shape[2:]} -> {ex.target.shape} differ "
                             f"from the dataset's {self.n_in} -> {self.n_out}")
        return ex

    def __len__(self) -> int:
        return len(self._examples) or len(self._paths)

    def example(self, i: int) -> Example:
        return self._examples[i] if self._examples else self._check(read_shard(self._paths[i]))

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        """Example i with all its views: inputs (V, 2, n^3), depth (V, 2, d, d), target (m^3)."""
        ex = self.example(i)
        item = {"inputs": torch.from_numpy(ex.inputs).float(),
                "target": torch.from_numpy(ex.target).float()}
        if ex.depth is not None:
            item["depth"] = torch.from_numpy(ex.depth)
        return item

    def batch(self, indices: Sequence[int], views: Sequence[Sequence[int]]) -> Batch:
        """Examples ``indices`` with the given views each (every list of the same length)."""
        exs = [self.example(i) for i in indices]
        inputs = np.stack([ex.inputs[list(v)] for ex, v in zip(exs, views, strict=True)])
        target = np.stack([ex.target for ex in exs])[:, None]
        depth = None
        if all(ex.depth is not None for ex in exs):
            depth = torch.from_numpy(np.stack([ex.depth[list(v)]  # type: ignore[index]
                                               for ex, v in zip(exs, views, strict=True)]))
        return Batch(torch.from_numpy(inputs).float(), depth, torch.from_numpy(target).float())

    def view_counts(self) -> list[int]:
        """V of every example (from each shard's ``inputs`` alone when lazy)."""
        if self._examples:
            return [ex.n_views for ex in self._examples]
        return [_shard_views(p) for p in self._paths]


def _shard_views(path: Path) -> int:
    try:
        with np.load(path, allow_pickle=False) as z:
            return int(z["inputs"].shape[0])
    except (OSError, ValueError, KeyError) as exc:
        raise ShardError(path, str(exc)) from exc


def sample_views(n_views: int, k: int, rng: np.random.Generator) -> list[int]:
    """k of n_views views: the first (the grid's reference camera) and k - 1 others, in order."""
    rest = rng.choice(np.arange(1, n_views), size=k - 1, replace=False)
    return [0, *sorted(int(r) for r in rest)]


def training_batch(data: CompletionDataset, counts: Sequence[int], step: int, batch_size: int,
                   max_views: int, seed: int, surface_dropout: float = 0.0,
                   mirror: float = 0.0) -> Batch:
    """The batch of training step ``step``: a pure function of (seed, step).

    The batch shares one view count k: 1 with probability one half (the single scan is the
    headline setting), else uniform in 2..max_views. Examples recorded with exactly k views are
    taken whole where the data has them, since their grid was placed from exactly those views;
    otherwise examples with more views keep their first view and a random ordered subset of
    k - 1 others. Examples are drawn with replacement.

    With ``surface_dropout`` > 0, each example loses a share of its seen-surface voxels drawn
    uniformly up to that share (they become unknown): a part far away or behind others is seen
    by fewer pixels, and the network must not need every surface voxel.

    With ``mirror`` > 0, that share of the examples is mirrored across the observer's right
    axis (grid x), every view, depth view and the truth alike: the grid is Z up and yawed to
    the first camera, so the mirror image is a mirrored part seen by a mirrored camera.

    Args:
        counts: the view count of every example (``data.view_counts()``, computed once).
    """
    rng = np.random.default_rng([seed, step, 1])
    top = min(max_views, max(counts))
    k = 1 if top == 1 or rng.random() < 0.5 else int(rng.integers(2, top + 1))
    exact = [i for i, c in enumerate(counts) if c == k]
    pool = exact or [i for i, c in enumerate(counts) if c > k]
    indices = [int(i) for i in rng.choice(pool, size=batch_size)]
    if exact:
        batch = data.batch(indices, [list(range(k))] * batch_size)
    else:
        batch = data.batch(indices, [sample_views(counts[i], k, rng) for i in indices])
    if mirror > 0:
        flip = torch.from_numpy(rng.random(batch_size) < mirror)
        inputs, target = batch.inputs.clone(), batch.target.clone()
        inputs[flip] = inputs[flip].flip(-3)  # x of (n, n, n)
        target[flip] = target[flip].flip(-3)
        depth = batch.depth
        if depth is not None:
            depth = depth.clone()
            depth[flip] = depth[flip].flip(-2)  # x of the (x, z) depth cells
        batch = Batch(inputs, depth, target)
    if surface_dropout <= 0:
        return batch
    drop = rng.uniform(0.0, surface_dropout, size=(batch_size, 1, 1, 1, 1))
    keep = rng.random(batch.inputs[:, :, 0].shape) >= drop  # (B, V, n, n, n)
    inputs = batch.inputs.clone()
    inputs[:, :, 0] *= torch.from_numpy(keep).float()
    return Batch(inputs, batch.depth, batch.target)


def eval_batches(data: CompletionDataset, counts: Sequence[int], batch_size: int,
                 n_views: int) -> list[tuple[list[int], list[list[int]]]]:
    """Fixed evaluation batches, grouped so each batch shares one view count; returns
    (indices, views) pairs.

    Where the data holds examples recorded with exactly ``n_views`` views, those alone are
    evaluated, whole: an example of more views cut to its first ones keeps a grid placed from
    all of them, extents that the views kept could not give. Otherwise every example is
    evaluated with its first n_views views (fewer if it has fewer).
    """
    exact = [i for i, c in enumerate(counts) if c == n_views]
    by_k: dict[int, list[int]] = {n_views: exact} if exact else {}
    for i, c in enumerate(counts if not exact else ()):
        by_k.setdefault(min(c, n_views), []).append(i)
    out = []
    for k, idx in sorted(by_k.items()):
        for s in range(0, len(idx), batch_size):
            chunk = idx[s:s + batch_size]
            out.append((chunk, [list(range(k))] * len(chunk)))
    return out
