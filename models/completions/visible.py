"""``visible``: the seen surface alone, as the camera gave it (no learning)."""

from __future__ import annotations

from cadio.registry import Role
from models.completions import COMPLETIONS, CompletionMethod

VISIBLE = COMPLETIONS.register(CompletionMethod(
    "visible", "the seen surface alone (no completion)", Role.BASELINE, 1, __name__,
    solid=lambda example: example.visible))
