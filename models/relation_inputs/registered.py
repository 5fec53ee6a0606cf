"""``registered``: the CAD's surface samples at the poses registration found in the scan.

The as-built route's input (``cadio.inspect``): each part of an inspection capture registered
from the scan alone (the search route: no design pose reaches it), then read like ``truth``:
its CAD samples with their faces' exact normals at the registered pose, decided by the
``truth`` networks and the exact tests, each pair's evidence read within its two poses'
uncertainty (their shift sigmas combined; ``models.geometric.within_pose``): the CAD's 0.1 mm
asks more than a pose registered in a D435's depth can say. Copies of a shape (which bolt of
six, which ball of a ring) are scored as the part whose points they registered, as BOP scores
interchangeable instances: which copy is which is left open by a symmetric assembly, and the
names the search gives them are scored on their own (``inspect_pose_summary.csv``'s
``named``). ``registered_cad`` reads the same poses at the CAD's tolerances. Its pair views
come from the inspection stage (``cadio.evidence.pairs.posed_pair_views``), never from a
night's other captures.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from cadio.registry import Role
from models.relation_inputs import INPUTS, InputContext, RelationInput

if TYPE_CHECKING:
    from cadio.evidence.pairs import InputBuilder
    from cadio.workspace import Workspace


def builder(capture: Path, ws: Workspace, ctx: InputContext) -> InputBuilder | None:
    return None  # its pair views are made where the registration is (the inspection)


REGISTERED = INPUTS.register(RelationInput(
    "registered", "the CAD's surface samples at the poses found in the scan, without the "
    "design, read within the poses' uncertainty", 3, __name__, builder, role=Role.BASELINE,
    exact=True, networks="truth", trained=False))
