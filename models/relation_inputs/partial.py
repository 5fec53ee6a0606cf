"""``partial``: the segmented observed points of the view, what the camera saw of each part."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from models.relation_inputs import INPUTS, InputContext, RelationInput

if TYPE_CHECKING:  # the evidence's modules load where a night builds pairs
    from cadio.evidence.pairs import InputBuilder, InputClouds, ViewSources
    from cadio.workspace import Workspace


def observed_clouds(src: ViewSources) -> InputClouds:
    from cadio.evidence.pairs import InputClouds

    return InputClouds(src.observed)


def builder(capture: Path, ws: Workspace, ctx: InputContext) -> InputBuilder:
    return observed_clouds


PARTIAL = INPUTS.register(RelationInput(
    "partial", "the observed points of the view", 1, __name__, builder))
