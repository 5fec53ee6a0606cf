"""``truth``: points sampled on the parts' CAD surfaces, placed as the capture placed them.

The upper bound of the relation methods: the evidence is measured on the CAD samples with
their faces' exact normals (``cadio.evidence.cad_samples``), the centres are the solids'.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from models.relation_inputs import INPUTS, InputContext, RelationInput

if TYPE_CHECKING:  # the evidence's modules load where a night builds pairs
    from cadio.evidence.pairs import InputBuilder, InputClouds, ViewSources
    from cadio.workspace import Workspace


def truth_clouds(src: ViewSources) -> InputClouds:
    from cadio.evidence.pairs import InputClouds

    a, b = src.placed
    return InputClouds(np.stack([a.truth, b.truth]), (a.dense, b.dense),
                       np.stack([a.centre, b.centre]))


def builder(capture: Path, ws: Workspace, ctx: InputContext) -> InputBuilder:
    return truth_clouds


TRUTH = INPUTS.register(RelationInput(
    "truth", "the CAD's surface samples at the true poses (the upper bound)", 0, __name__,
    builder, exact=True))
