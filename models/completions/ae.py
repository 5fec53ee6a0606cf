"""``ae``: the generator of ``gan_lstm`` without its LSTM and critic (the ablation).

Without an LSTM it sees one grid: the union of a sequence's views, in training as in scoring.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy.typing as npt

from cadio.registry import Role
from models.completions import COMPLETIONS, CompletionMethod

if TYPE_CHECKING:
    from cadio.capture.examples import Example


def union_input(example: Example) -> npt.NDArray[Any]:
    """(1, 2, n, n, n): the union of the example's views' states."""
    from cadio.capture.observe import union_states

    union: npt.NDArray[Any] = union_states(example.inputs)[None]
    return union


AE = COMPLETIONS.register(CompletionMethod(
    "ae", "the generator without LSTM and critic, on the union of the views",
    Role.BASELINE, 3, __name__, model_input=union_input,
    config="models.completion:CompletionConfig", defaults={"lstm": False, "gan": False}))
