"""``ltn``: the paper's Logic Tensor Network, the relation method the product ships.

A grounding MLP over each part's points and the pair's evidence, one Neural Tensor Network
predicate per relation, trained on the facts and the fuzzy axioms (converses, asymmetry,
symmetry, exclusion) as LTNtorch aggregates them (``models.relations``,
``models.relation_logic``).
"""

from __future__ import annotations

from cadio.registry import Role
from models.relation_methods import RELATION_METHODS, RelationMethod

LTN = RELATION_METHODS.register(RelationMethod(
    "ltn", "Logic Tensor Network: grounding MLP and NTN predicates, facts and fuzzy axioms",
    Role.OURS, 0, __name__, axioms=True))
