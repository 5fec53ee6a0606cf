"""How a relation network's scores become answers: per-relation decision thresholds and
temperatures, fitted on validation pairs.

The fact axioms weigh a rare relation's positives and negatives alike, so a score of 0.5
over-predicts it: each relation's threshold maximises its F1 on validation, and a temperature
about that threshold calibrates its confidence. Converse relations share both, so a pair and
its swap get the same decisions and confidences.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from models.relations import OPPOSITES, RELATIONS

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
