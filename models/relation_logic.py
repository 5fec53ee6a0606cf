"""The relation network's logic: product real logic and the knowledge bases it is trained on.

``knowledge_base`` (the ten relations' facts and, for ``ltn``, the paper's rules) and
``joint_knowledge_base`` (the joint head's facts and what each joint says of the face mates)
give the satisfaction that ``models.relations_train`` maximises. Operators and aggregators are
LTNtorch's, written out. No I/O here.
"""

from __future__ import annotations

import torch
from torch import Tensor

from models.relation_methods import uses_axioms
from models.relations import (
    CONVERSE_INDEX,
    DIRECTIONAL_INDEX,
    JOINT_IMPLIES,
    JOINTS,
    PARALLEL,
    PERPENDICULAR,
    RELATIONS,
    SYMMETRIC_INDEX,
    RelationConfig,
)

# Fuzzy semantics: product real logic with LTNtorch's stable operators (ltn/fuzzy_ops.py:
# NotStandard, AndProd, OrProbSum, ImpliesReichenbach, AggregPMean, AggregPMeanError). Six
# one-line functions rather than a new dependency; the projections pi_0 and pi_1 keep operands
# off 0 and 1 where the gradient of a product or of a p-th root would vanish or explode.
EPS = 1e-4  # LTNtorch's eps


def _pi0(x: Tensor) -> Tensor:
    return (1 - EPS) * x + EPS  # [0, 1] -> (0, 1]


def _pi1(x: Tensor) -> Tensor:
    return (1 - EPS) * x  # [0, 1] -> [0, 1)


def not_(a: Tensor) -> Tensor:
    """Standard negation 1 - a."""
    return 1 - a


def and_(a: Tensor, b: Tensor) -> Tensor:
    """Product t-norm a b (stable: both operands through pi_0)."""
    return _pi0(a) * _pi0(b)


def or_(a: Tensor, b: Tensor) -> Tensor:
    """Probabilistic sum a + b - a b (stable: both operands through pi_1)."""
    a, b = _pi1(a), _pi1(b)
    return a + b - a * b


def implies(a: Tensor, b: Tensor) -> Tensor:
    """Reichenbach implication 1 - a + a b (stable: a through pi_0, b through pi_1)."""
    a, b = _pi0(a), _pi1(b)
    return 1 - a + a * b


def forall(x: Tensor, p: float) -> Tensor:
    """p-mean-error aggregation 1 - mean((1 - x)^p)^(1/p) over all of x: a scalar."""
    return 1 - (1 - _pi1(x)).pow(p).mean().pow(1 / p)


def exists(x: Tensor, p: float) -> Tensor:
    """p-mean aggregation mean(x^p)^(1/p) over all of x: a scalar."""
    return _pi0(x).pow(p).mean().pow(1 / p)


def weighted_forall(x: Tensor, weights: Tensor, p: float) -> Tensor:
    """``forall`` with a weight per element (the KB's aggregation of its axioms): a scalar."""
    err = (1 - _pi1(x)).pow(p)
    return 1 - ((err * weights).sum() / weights.sum()).pow(1 / p)


def knowledge_base(t_ab: Tensor, t_ba: Tensor, labels: Tensor, cfg: RelationConfig
                   ) -> dict[str, Tensor]:
    """Satisfaction of the knowledge base on a batch, and of its facts and rules apart.

    Facts: for every relation, Forall over the positives of r(a, b) and Forall over the
    negatives of Not r(a, b), as two axioms: a relation positive in 10% of pairs would otherwise
    be satisfied 90% by predicting False everywhere. Rules (``ltn`` only), each a Forall over
    the batch's pairs and their swaps: converse r(x) -> conv(r)(swap x) for the six directional
    relations (over a domain closed under swapping, these are both implications of each
    equivalence), asymmetry r(x) -> Not r(swap x), symmetry of the four symmetric relations,
    and Not(parallel(x) And perpendicular(x)).

    Args:
        t_ab, t_ba: (B, 10) truth values in [0, 1] of (a, b) and (b, a).
        labels: (B, 10) 0/1 of (a, b).

    Returns:
        "sat", "facts", "rules": scalars in [0, 1] ("rules" is 1 for ``mlp``).
    """
    p = cfg.p_forall
    facts = []
    for r in range(len(RELATIONS)):
        pos = labels[:, r] > 0.5
        for holds, mask in ((t_ab[:, r], pos), (not_(t_ab[:, r]), ~pos)):
            if bool(mask.any()):  # an empty class has no axiom in this batch
                facts.append(forall(holds[mask], p))
    rules = []
    if uses_axioms(cfg.method):
        t, s = torch.cat([t_ab, t_ba]), torch.cat([t_ba, t_ab])  # (2B, 10): x and swap x
        for r in DIRECTIONAL_INDEX:
            rules.append(forall(implies(t[:, r], s[:, CONVERSE_INDEX[r]]), p))
            rules.append(forall(implies(t[:, r], not_(s[:, r])), p))
        rules += [forall(implies(t[:, r], s[:, r]), p) for r in SYMMETRIC_INDEX]
        rules.append(forall(not_(and_(t[:, PARALLEL], t[:, PERPENDICULAR])), p))
    axioms = torch.stack(facts + rules)
    weights = torch.tensor([1.0] * len(facts) + [cfg.rule_weight] * len(rules),
                           device=axioms.device)
    one = axioms.new_ones(())
    return {"sat": weighted_forall(axioms, weights, cfg.p_sat),
            "facts": weighted_forall(torch.stack(facts), weights[:len(facts)], cfg.p_sat),
            "rules": forall(torch.stack(rules), cfg.p_sat) if rules else one}


def joint_knowledge_base(joint_probs: Tensor, joints: Tensor, t_ab: Tensor,
                         cfg: RelationConfig) -> Tensor:
    """Satisfaction of the joint head's own knowledge base on a batch: a scalar in [0, 1].

    Facts: for every joint, Forall over its pairs of the joint's probability (pairs whose joint
    is unknown, -1, take no part). Rules (``ltn`` only), each a Forall over the batch:
    joint(x) -> each face mate it implies (``JOINT_IMPLIES``), the relation's truth value read
    as it is (``joint_detach``: without training the relation) or trained along. Kept apart
    from ``knowledge_base`` (its own term of the loss): in one aggregate the joint's errors
    rescale the relations' gradients.

    Args:
        joint_probs: (B, ``JOINTS``) the joint head's probabilities.
        joints: (B,) each pair's joint as an index into ``JOINTS``, -1 where unknown.
        t_ab: (B, 10) the relations' truth values of (a, b).
    """
    p = cfg.p_forall
    axioms = [forall(joint_probs[joints == c, c], p) for c in range(len(JOINTS))
              if bool((joints == c).any())]
    n_facts = len(axioms)
    if uses_axioms(cfg.method):
        rel = t_ab.detach() if cfg.joint_detach else t_ab
        for c, name in enumerate(JOINTS):
            for r, positive in JOINT_IMPLIES[name]:
                then = rel[:, r] if positive else not_(rel[:, r])
                axioms.append(forall(implies(joint_probs[:, c], then), p))
    if not axioms:
        return joint_probs.new_ones(())
    weights = torch.tensor([1.0] * n_facts + [cfg.rule_weight] * (len(axioms) - n_facts),
                           device=joint_probs.device)
    return weighted_forall(torch.stack(axioms), weights, cfg.p_sat)
