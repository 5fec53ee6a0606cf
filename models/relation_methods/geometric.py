"""``geometric``: fixed tests on the pair's evidence, no learning (``models.geometric``).

Each CAD definition with its tolerances widened by what the points resolve (except where the
input is the CAD's own samples); the directional relations on the parts' centres.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from cadio.registry import Role
from models.relation_methods import RELATION_METHODS, RelationMethod


def decide(*args: Any) -> npt.NDArray[np.bool_]:
    from models.geometric import geometric_decisions

    return geometric_decisions(*args)


GEOMETRIC = RELATION_METHODS.register(RelationMethod(
    "geometric", "fixed tests on the pair evidence (CAD tolerances widened by the point "
    "spacing)", Role.BASELINE, 2, __name__, decide=decide))
