"""``mlp``: the network of ``ltn`` trained on the facts only (no axioms): the rules' ablation."""

from __future__ import annotations

from cadio.registry import Role
from models.relation_methods import RELATION_METHODS, RelationMethod

MLP = RELATION_METHODS.register(RelationMethod(
    "mlp", "the same network on the facts only (no axioms)", Role.BASELINE, 1, __name__))
