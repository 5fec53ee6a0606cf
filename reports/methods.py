"""What the reports read of the method registries: the product's methods and the tables' order.

The registries (``models.completions``, ``models.relation_methods``, ``models.relation_inputs``)
import no torch and no CAD kernel, so the reports stay light; a method registered there shows
in every table, check and plot without an edit here.
"""

from __future__ import annotations

# The protocol the checks and the headline follow: the input grid placed from what the camera
# knows (``cadio.capture.examples.OBSERVED``; not imported: the capture room loads open3d).
OBSERVED = "observed"


def completion_ours() -> tuple[str, str]:
    """(method, protocol) of the completion the product ships, which the checks follow."""
    from models.completions import ours

    return ours().name, OBSERVED


def completion_order() -> tuple[str, ...]:
    """The completion methods in the tables' order: the product's first, then its baselines."""
    from models.completions import COMPLETIONS

    return COMPLETIONS.names()


def method_labels() -> dict[str, str]:
    """How the tables a person reads name the completion methods where it is not their name
    (``CompletionMethod.label``: r2n2 is labelled surface-only); the files keep the names."""
    from models.completions import COMPLETIONS

    return {m.name: m.label for m in COMPLETIONS.entries() if m.label != m.name}


def product() -> tuple[str, str]:
    """(input, method) of the product's relation answers: the assembly table, the checks and
    the exported notes read these rows."""
    from models.relation_inputs import product as product_input
    from models.relation_methods import ours

    return product_input().name, ours().name


def relation_method_order() -> tuple[str, ...]:
    from models.relation_methods import RELATION_METHODS

    return RELATION_METHODS.names()


def input_order() -> tuple[str, ...]:
    from models.relation_inputs import INPUTS

    return INPUTS.names()
