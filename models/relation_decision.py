"""How a relation network's scores become answers: a pair and its swap decided together
(``combine``, ``decide``; ``violations`` of the raw outputs), with per-relation decision
thresholds and temperatures fitted on validation pairs.

The fact axioms weigh a rare relation's positives and negatives alike, so a score of 0.5
over-predicts it: each relation's threshold maximises its F1 on validation, and a temperature
about that threshold calibrates its confidence. Converse relations share both, so a pair and
its swap get the same decisions and confidences.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from models.relations import (
    CONVERSE_INDEX,
    DIRECTIONAL_INDEX,
    EXCLUSIVE,
    OPPOSITES,
    PARALLEL,
    PERPENDICULAR,
    RELATIONS,
)

BoolArray = npt.NDArray[np.bool_]
FloatArray = npt.NDArray[np.floating]
G = TypeVar("G", bound=np.generic)

_T_GRID = np.exp(np.linspace(np.log(0.05), np.log(20.0), 241))  # temperatures tried
_THRESHOLDS = np.linspace(0.05, 0.95, 91)  # decision thresholds tried


def _logit(p: npt.NDArray[np.floating]) -> npt.NDArray[np.float64]:
    p = np.clip(np.asarray(p, dtype=np.float64), 1e-7, 1 - 1e-7)
    return np.log(p) - np.log1p(-p)


def calibrate(score: npt.NDArray[np.floating], temperatures: npt.ArrayLike,
              thresholds: npt.ArrayLike | None = None) -> npt.NDArray[np.float64]:
    """Calibrated probabilities sigmoid((logit(score) - logit(t)) / T) per relation: (N, 10);
    0.5 exactly at each relation's decision threshold t (default 0.5)."""
    t = np.asarray(temperatures, dtype=np.float64)
    shift = 0.0 if thresholds is None else _logit(np.asarray(thresholds))
    return 1 / (1 + np.exp(-(_logit(score) - shift) / t))


def _groups() -> list[list[int]]:
    """Columns that share a threshold and a temperature: converse pairs, then the rest."""
    groups = [list(p) for p in OPPOSITES]
    return groups + [[r] for r in range(len(RELATIONS)) if all(r not in g for g in groups)]


def fit_thresholds(score: npt.NDArray[np.floating], labels: npt.NDArray[np.bool_]
                   ) -> npt.NDArray[np.float64]:
    """Per-relation decision thresholds maximising F1 on labelled scores (converse relations
    share one, fitted on both columns); 0.5 for a relation without positives. The highest
    threshold among equally good ones is kept (fewer false mates)."""
    s, y = np.asarray(score, dtype=np.float64), np.asarray(labels, dtype=bool)
    out = np.full(len(RELATIONS), 0.5)
    for cols in _groups():
        ss, yy = s[:, cols].ravel(), y[:, cols].ravel()
        if not yy.any():
            continue
        pred = ss[None] > _THRESHOLDS[:, None]  # (G, M)
        tp = (pred & yy).sum(1)
        f1 = 2 * tp / np.maximum(pred.sum(1) + yy.sum(), 1)
        out[cols] = _THRESHOLDS[len(f1) - 1 - int(np.argmax(f1[::-1]))]
    return out


def fit_temperatures(score: npt.NDArray[np.floating], labels: npt.NDArray[np.bool_],
                     thresholds: npt.ArrayLike | None = None) -> npt.NDArray[np.float64]:
    """Per-relation temperatures minimising the log loss of ``calibrate`` on labelled scores.

    Converse relations share one temperature (fitted on both columns), so that the confidences
    of a pair's swap are exactly the swapped confidences. A grid over [0.05, 20]: 1-D, exact
    enough and deterministic.
    """
    shift = 0.0 if thresholds is None else _logit(np.asarray(thresholds))
    z, y = _logit(score) - shift, np.asarray(labels, dtype=np.float64)
    temps = np.ones(len(RELATIONS))
    for cols in _groups():
        zz, yy = z[:, cols].ravel()[None], y[:, cols].ravel()[None]  # (1, M)
        s = zz / _T_GRID[:, None]  # (G, M)
        nll = (np.logaddexp(0, s) - yy * s).mean(1)  # log loss of sigmoid(s)
        temps[cols] = _T_GRID[int(np.argmin(nll))]
    return temps


@dataclass(frozen=True)
class Decision:
    """How a network's scores become answers: per-relation temperatures and thresholds."""

    temperatures: npt.NDArray[np.float64]
    thresholds: npt.NDArray[np.float64]

    @classmethod
    def default(cls) -> Decision:
        return cls(np.ones(len(RELATIONS)), np.full(len(RELATIONS), 0.5))


def f1_scores(decided: npt.NDArray[np.bool_], truth: npt.NDArray[np.bool_]
              ) -> npt.NDArray[np.float64]:
    """(10,) F1 of each relation's decisions (1 where a relation has neither positives nor
    predictions)."""
    tp = (decided & truth).sum(0)
    total = decided.sum(0) + truth.sum(0)
    return np.where(total > 0, 2 * tp / np.maximum(total, 1), 1.0)


def swap_decision(decided: npt.NDArray[G]) -> npt.NDArray[G]:
    """Per-relation values of (a, b) -> those of (b, a): the converse columns swapped, (N, 10)."""
    return decided[:, list(CONVERSE_INDEX)]


def combine(raw_ab: FloatArray, raw_ba: FloatArray) -> FloatArray:
    """The pair's score of each relation of (a, b), from both orders' outputs: (N, 10).

    Directional r: mean of r(a, b) and conv(r)(b, a); symmetric r: mean of r(a, b) and
    r(b, a). The swapped pair's scores are exactly ``swap_decision`` of these (the two terms
    are the same numbers, and float addition commutes).
    """
    ab, ba = np.asarray(raw_ab, dtype=np.float64), np.asarray(raw_ba, dtype=np.float64)
    return (ab + swap_decision(ba)) / 2


def decide(score: FloatArray, thresholds: npt.ArrayLike | None = None) -> BoolArray:
    """Relations that hold, (N, 10) bool, from ``combine``'s scores.

    A score above its relation's threshold (default 0.5; fitted on validation by
    ``relations_train.fit_thresholds``) holds, except that of each exclusive pair (left/right,
    above/below, front/behind, parallel/perpendicular) only the one further above its threshold
    may hold; on an exact tie neither does (any other choice would break the converse rule on
    the swapped pair, whose converse relations share one threshold).
    """
    score = np.asarray(score)
    t = np.full(score.shape[-1], 0.5) if thresholds is None else np.asarray(thresholds)
    decided = score > t
    margin = score - t
    for i, j in EXCLUSIVE:
        both = decided[:, i] & decided[:, j]
        decided[:, i] &= ~both | (margin[:, i] > margin[:, j])
        decided[:, j] &= ~both | (margin[:, j] > margin[:, i])
    return decided


def violations(raw_ab: FloatArray, raw_ba: FloatArray, threshold: float = 0.5) -> BoolArray:
    """Where the thresholded raw outputs break a rule involving each relation: (N, 10) bool.

    Directional r: r(a, b) disagrees with conv(r)(b, a), or r holds both ways. Symmetric r:
    r(a, b) disagrees with r(b, a). Parallel and perpendicular: also both holding for (a, b)
    or for (b, a).
    """
    a, b = np.asarray(raw_ab) > threshold, np.asarray(raw_ba) > threshold
    out = a != swap_decision(b)
    d = list(DIRECTIONAL_INDEX)
    out[:, d] |= a[:, d] & b[:, d]
    clash = (a[:, PARALLEL] & a[:, PERPENDICULAR]) | (b[:, PARALLEL] & b[:, PERPENDICULAR])
    out[:, [PARALLEL, PERPENDICULAR]] |= clash[:, None]
    return out
