"""Intervals of the night's figures that resample the units they rest on.

The views of one pair are not independent: one pair seen from eight cameras is one mistake
eight times. So each interval of an assembly or relation figure draws the distinct pairs with
replacement, each with all its views ((a, b) and (b, a) are one pair), and reads the figure's
quantiles over the draws. Likewise the parts of one file are not independent (one file gives
28 balls of one bearing), so the completion headline's interval draws source files, each with
all its parts. Pure NumPy and pandas: the verdict reads them too.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pandas as pd

LEVEL = 0.95
DRAWS = 2000


def _pair_key(scene: pd.Series, a: pd.Series, b: pd.Series) -> pd.Series:
    """One key per distinct pair of a scene: (a, b) and (b, a) alike."""
    a, b = a.astype(str), b.astype(str)
    return scene.astype(str) + "|" + a.where(a <= b, b) + "|" + b.where(a <= b, a)


def _resampled(per_unit: npt.NDArray[np.float64], draws: int, seed: int
               ) -> npt.NDArray[np.float64]:
    """(draws, columns) sums of per-unit values (units, columns) over resamples of the units
    (pairs, files) with replacement."""
    rng = np.random.default_rng(seed)
    units = len(per_unit)
    pick = rng.integers(0, units, size=(draws, units))
    times = np.zeros((draws, units))  # how often each draw picked each unit
    np.add.at(times, (np.repeat(np.arange(draws), units), pick.ravel()), 1.0)
    return np.asarray(times @ per_unit, dtype=np.float64)


def _tails(values: npt.NDArray[np.float64], level: float) -> tuple[float, float]:
    values = values[np.isfinite(values)]
    if not len(values):
        return math.nan, math.nan
    tail = (1.0 - level) / 2
    return float(np.quantile(values, tail)), float(np.quantile(values, 1 - tail))


def joint_interval(joints: pd.DataFrame, level: float = LEVEL, draws: int = DRAWS,
                   seed: int = 0) -> tuple[float, float, int]:
    """A ``level`` interval of the joint agreement (the mean of ``agree`` over views) and the
    number of distinct pairs it rests on. The views of one pair are not independent (one pair
    seen from eight cameras is one mistake eight times), so the interval resamples the pairs
    with replacement, each with all its views; (a, b) and (b, a) are one pair.

    Args:
        joints: ``assembly_joints.csv``'s rows (assembly, part_a, part_b, agree).

    Returns:
        (low, high, pairs); NaNs and 0 without rows.
    """
    if not len(joints):
        return math.nan, math.nan, 0
    key = _pair_key(joints["assembly"], joints["part_a"], joints["part_b"])
    per_pair = joints.assign(_pair=key).groupby("_pair")["agree"].agg(["sum", "size"])
    sums = _resampled(per_pair.to_numpy(float), draws, seed)
    return (*_tails(sums[:, 0] / sums[:, 1], level), len(per_pair))


def accuracy_interval(rows: pd.DataFrame, level: float = LEVEL, draws: int = DRAWS,
                      seed: int = 0) -> tuple[float, float, int]:
    """A ``level`` interval of the relation accuracy (each relation's accuracy over the pair
    views, then the mean over relations, as the verdict's ``relation_accuracy``) and the number
    of distinct pairs; the pairs are resampled as in ``mates_f1_interval``.

    Args:
        rows: ``relations_pairs`` rows of one input, method and category (scene, part_a,
            part_b, relation, truth, predicted).

    Returns:
        (low, high, pairs); NaNs and 0 without rows.
    """
    if not len(rows):
        return math.nan, math.nan, 0
    right = (rows["truth"].astype(bool) == rows["predicted"].astype(bool)).to_numpy()
    sums, pairs = _per_pair_relation(rows, np.column_stack([right, np.ones(len(rows))]), draws,
                                     seed)
    held = sums[..., 1] > 0
    accuracy = np.where(held, sums[..., 0] / np.maximum(sums[..., 1], 1), 0.0)
    n = held.sum(axis=1)
    means = np.where(n > 0, accuracy.sum(axis=1) / np.maximum(n, 1), np.nan)
    return (*_tails(means, level), pairs)


def _per_pair_relation(rows: pd.DataFrame, counts: npt.NDArray[np.float64], draws: int,
                       seed: int) -> tuple[npt.NDArray[np.float64], int]:
    """(draws, relations, columns) sums of per-row ``counts`` (rows, columns) over resamples
    of the distinct pairs, each with all its views and relations; and the number of pairs."""
    pair, _ = pd.factorize(_pair_key(rows["scene"], rows["part_a"], rows["part_b"]), sort=True)
    relation, _ = pd.factorize(rows["relation"].astype(str), sort=True)
    pairs, relations = int(pair.max()) + 1, int(relation.max()) + 1
    per_pair = np.zeros((pairs, relations, counts.shape[1]))
    np.add.at(per_pair, (pair, relation), counts)
    sums = _resampled(per_pair.reshape(pairs, -1), draws, seed)
    return sums.reshape(draws, relations, counts.shape[1]), pairs


def f1_interval(rows: pd.DataFrame, level: float = LEVEL, draws: int = DRAWS,
                seed: int = 0) -> tuple[float, float, int]:
    """A ``level`` interval of the F1 of one relation's answers over pair views, and the number
    of distinct pairs: ``mates_f1_interval`` of the rows as a single relation. Resamples
    without a positive either way (F1 undefined) are left out.

    Args:
        rows: ``relations_pairs`` rows of one relation (scene, part_a, part_b, truth,
            predicted).

    Returns:
        (low, high, pairs); NaNs where F1 is undefined in every resample, and 0 without rows.
    """
    return mates_f1_interval(rows.assign(relation=""), level, draws, seed)


def mates_f1_interval(rows: pd.DataFrame, level: float = LEVEL, draws: int = DRAWS,
                      seed: int = 0) -> tuple[float, float, int]:
    """A ``level`` interval of the mates F1 (the mean over relations of each relation's F1, as
    the verdict's ``mates_f1``) and the number of distinct pairs. As ``joint_interval``: the
    pairs are resampled, each with all its views (its true and false positives and false
    negatives together), one draw of pairs for every relation. A relation whose F1 is undefined
    in a draw is left out of that draw's mean.

    Args:
        rows: ``relations_pairs`` rows of one input and method in the assemblies (scene,
            part_a, part_b, relation, truth, predicted).

    Returns:
        (low, high, pairs); NaNs and 0 without rows.
    """
    if not len(rows):
        return math.nan, math.nan, 0
    t, p = rows["truth"].astype(bool), rows["predicted"].astype(bool)
    # per pair and relation: true positives, false ones, misses
    sums, pairs = _per_pair_relation(
        rows, np.column_stack([t & p, ~t & p, t & ~p]).astype(np.float64), draws, seed)
    denominator = 2 * sums[..., 0] + sums[..., 1] + sums[..., 2]
    defined = denominator > 0
    f1 = np.where(defined, 2 * sums[..., 0] / np.maximum(denominator, 1), 0.0)
    n = defined.sum(axis=1)
    means = np.where(n > 0, f1.sum(axis=1) / np.maximum(n, 1), np.nan)
    return (*_tails(means, level), pairs)


def shape_mean_interval(values: npt.ArrayLike, shapes: npt.ArrayLike, files: npt.ArrayLike,
                        level: float = LEVEL, draws: int = DRAWS, seed: int = 0
                        ) -> tuple[float, float, int]:
    """A ``level`` interval of a mean per distinct shape (each shape the mean of its parts'
    values, then the mean over shapes) and the number of source files it rests on. Files are
    drawn with replacement, each with all its parts; a shape no drawn file holds is left out of
    that draw's mean.

    Args:
        values: (parts,) one value per part (NaN: the part is left out).
        shapes: (parts,) each part's shape key; files: (parts,) its source file.

    Returns:
        (low, high, files); NaNs and 0 without a part.
    """
    frame = pd.DataFrame({"v": np.asarray(values, dtype=np.float64), "s": np.asarray(shapes),
                          "f": np.asarray(files)}).dropna(subset=["v"])
    if not len(frame):
        return math.nan, math.nan, 0
    shape, _ = pd.factorize(frame["s"], sort=True)
    file, _ = pd.factorize(frame["f"], sort=True)
    n_shapes, n_files = int(shape.max()) + 1, int(file.max()) + 1
    per_file = np.zeros((n_files, 2, n_shapes))  # per file and shape: sum of values, parts
    np.add.at(per_file, (file, 0, shape), frame["v"].to_numpy())
    np.add.at(per_file, (file, 1, shape), 1.0)
    sums = _resampled(per_file.reshape(n_files, -1), draws, seed).reshape(draws, 2, n_shapes)
    held = sums[:, 1] > 0
    means = np.where(held, sums[:, 0] / np.maximum(sums[:, 1], 1.0), 0.0)
    per_draw = means.sum(axis=1) / np.maximum(held.sum(axis=1), 1)
    return (*_tails(per_draw, level), n_files)
