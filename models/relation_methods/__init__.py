"""The relation methods: one module each, registered in ``RELATION_METHODS``.

A module registers a ``RelationMethod``: its name, role, a one-line summary, and how it
decides a pair's ten relations: a ``decide`` function of the pair's points and evidence for a
method without learning, or none for a network, whose checkpoints ``<name>-<input>.pt`` are
trained by ``mateqa train relations`` (with the fuzzy axioms beside the facts where
``axioms``). The relation stage, its report and checks, the training command and the model card
read this registry; nothing else lists the methods.

Importing this package imports no torch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from cadio.registry import Registry, Role

Decide = Callable[..., npt.NDArray[np.bool_]]


@dataclass(frozen=True)
class RelationMethod:
    """One relation method. ``module``: the registering module's ``__name__``.

    decide: for a method without learning, ``decide(points, mm_per_unit, features, keys,
    tests, centres) -> (N, 10) bool`` (``models.geometric.geometric_decisions``'s form); None
    for a network. axioms: a network trained on the rules beside the facts.
    """

    name: str
    summary: str
    role: Role
    order: int
    module: str
    decide: Decide | None = None
    axioms: bool = False

    @property
    def learned(self) -> bool:
        return self.decide is None


RELATION_METHODS: Registry[RelationMethod] = Registry("relation method", __name__)


def ours() -> RelationMethod:
    """The relation method the product ships (its role is ``ours``)."""
    (method,) = [m for m in RELATION_METHODS.entries() if m.role is Role.OURS]
    return method


def learned() -> tuple[str, ...]:
    """The names of the networks, in the registry's order."""
    return tuple(m.name for m in RELATION_METHODS.entries() if m.learned)


def uses_axioms(method: str) -> bool:
    """Whether a network of this method trains on the fuzzy axioms (an unknown name: no)."""
    return method in RELATION_METHODS and RELATION_METHODS.get(method).axioms


def decide_fixed(method: RelationMethod, *args: Any) -> npt.NDArray[np.bool_]:
    """A method without learning's decisions (``RelationMethod.decide``)."""
    assert method.decide is not None, method.name
    return method.decide(*args)
