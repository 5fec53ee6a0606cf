"""``registered_cad``: the ``registered`` input read at the CAD's own tolerances.

The same CAD samples at the same poses the search route found in the scan, without the pose's
uncertainty (``registered`` reads its pairs within it: ``models.geometric.within_pose``): the
figure the issue's "report at the CAD's tolerances too" asks for beside it. Its pair views come
from the inspection stage, as ``registered``'s.
"""

from __future__ import annotations

from cadio.registry import Role
from models.relation_inputs import INPUTS, RelationInput
from models.relation_inputs.registered import builder

REGISTERED_CAD = INPUTS.register(RelationInput(
    "registered_cad", "registered's poses read at the CAD's tolerances (0.1 mm), not within "
    "their uncertainty", 4, __name__, builder, role=Role.BASELINE, exact=True,
    networks="truth", trained=False))
