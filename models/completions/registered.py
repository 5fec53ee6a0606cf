"""``registered``: the library's CAD registered in the view, voxelized (no learning).

The QA team has the CAD of every part: the example's points are registered to each part of
its capture's bill of materials without any prior pose (the inspection's search route,
``cadio.inspect.completion``), and the best fit's CAD fills the cube. Not the paper's method:
the bound a completion from the library's own shapes reaches, beside the learned route.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from cadio.registry import Role
from models.completions import COMPLETIONS, BoolGrid, CompletionMethod

if TYPE_CHECKING:
    from cadio.capture.examples import Example
    from cadio.inspect.completion import CaptureCad


def _registered(example: Example, cad: CaptureCad) -> BoolGrid:
    from cadio.inspect.completion import registered_solid

    return registered_solid(example, cad)


REGISTERED = COMPLETIONS.register(CompletionMethod(
    "registered", "the library's CAD registered in the view without its pose (no learning)",
    Role.BASELINE, 5, __name__, from_cad=_registered))
