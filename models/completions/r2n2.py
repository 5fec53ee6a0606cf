"""``r2n2``: 3D-R2N2 (2D conv encoder, 3D conv-GRU, 3D decoder) on depth images of the seen
surface (``models.baselines``)."""

from __future__ import annotations

from cadio.registry import Role
from models.completions import COMPLETIONS, CompletionMethod

R2N2 = COMPLETIONS.register(CompletionMethod(
    "r2n2", "3D-R2N2 on depth images of the seen surface only, without the seen-free and "
    "unknown states the others read (surface-only: no fair baseline)", Role.BASELINE, 4,
    __name__,
    model_input=lambda example: example.depth, config="models.baselines:R2N2Config",
    display="r2n2 (surface only)"))
