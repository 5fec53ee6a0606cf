"""The relation inputs: one module each, registered in ``INPUTS``.

An input is what the relation methods read of a pair in a view: points of each part (the
CAD's, the camera's, a completion's ...). A module registers a ``RelationInput``: its name, a
one-line summary, and ``builder``: given a capture, the workspace and the night's
``InputContext``, the function that makes its clouds of each view of each pair
(``cadio.evidence.pairs.InputBuilder``), or None where the input has nothing for the capture.
Beside it, what the methods need to know of it: ``exact`` (its evidence is the CAD's own
samples with their faces' exact normals: the geometric tests take the CAD's tolerances, the
networks read the tests' answers), ``observed_by`` (its networks also read another input's
points and evidence of the same view), ``networks`` (whose checkpoints decide it, when not
its own) and ``trained`` (``mateqa train relations`` trains networks for it). The relation
stage, its report, the training command and the model card read this registry.

Importing this package imports no torch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cadio.registry import Registry, Role

if TYPE_CHECKING:
    from cadio.evidence.pairs import InputBuilder
    from cadio.workspace import Workspace


@dataclass(frozen=True)
class InputContext:
    """What a night hands the inputs' builders besides the capture: ``completion``, the
    completion network of the night (None without one), and ``surface``, how a completion is
    read as points (``models.relation_inputs.completed.voxel_surface`` by default)."""

    completion: Any = None
    surface: Any = None


Builder = Callable[[Path, "Workspace", InputContext], "InputBuilder | None"]


@dataclass(frozen=True)
class RelationInput:
    """One relation input. ``module``: the registering module's ``__name__``."""

    name: str
    summary: str
    order: int
    module: str
    builder: Builder
    role: Role = Role.BASELINE
    exact: bool = False
    observed_by: str | None = None
    networks: str | None = None
    trained: bool = True

    @property
    def checkpoints(self) -> str:
        """The input whose networks decide this one (its own unless ``networks``)."""
        return self.networks or self.name


INPUTS: Registry[RelationInput] = Registry("relation input", __name__)


def product() -> RelationInput:
    """The input the product's answers come from (its role is ``ours``)."""
    (spec,) = [i for i in INPUTS.entries() if i.role is Role.OURS]
    return spec


def trained() -> tuple[str, ...]:
    """The inputs the relation networks are trained for, in the registry's order."""
    return tuple(i.name for i in INPUTS.entries() if i.trained)


def builders(capture: Path, ws: Workspace, ctx: InputContext) -> dict[str, InputBuilder]:
    """Every input's builder for one capture (inputs with nothing for it left out)."""
    out = {}
    for spec in INPUTS.entries():
        build = spec.builder(capture, ws, ctx)
        if build is not None:
            out[spec.name] = build
    return out
