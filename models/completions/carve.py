"""``carve``: space carving behind the observed surface along the camera rays, by every view
given, above the support plane the camera saw (no learning; built with each example)."""

from __future__ import annotations

from cadio.registry import Role
from models.completions import COMPLETIONS, CompletionMethod

CARVE = COMPLETIONS.register(CompletionMethod(
    "carve", "space carving behind the seen surface, by every view (no learning)",
    Role.BASELINE, 2, __name__, solid=lambda example: example.carve))
