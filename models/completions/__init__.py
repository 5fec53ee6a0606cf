"""The completion methods: one module each, registered in ``COMPLETIONS``.

A module registers a ``CompletionMethod``: its name, role (the method the product ships, or a
baseline it is judged by), a one-line summary for tables, cards and ``--help``, and how it
completes an example: ``solid`` for a method without learning (the example carries what it
needs), ``from_cad`` for one that reads the library's CAD of the example's capture (its bill of
materials, scale, cameras and depth: ``cadio.inspect.completion.CaptureCad``; run where the
stage has the workspace), or ``model_input`` for a learned one, whose network is the checkpoint
``completion-<name>-<protocol>.pt`` of the night's folder and whose config is ``config`` with
``defaults``. The completion stage, the completion report, the checks, the training commands
and the model card read this registry; nothing else lists the methods.

Importing this package imports no torch: a method's module imports its network where it runs.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from cadio.registry import Registry, Role

if TYPE_CHECKING:
    from cadio.capture.examples import Example
    from cadio.inspect.completion import CaptureCad

BoolGrid = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class CompletionMethod:
    """One completion method. ``module``: the registering module's ``__name__``."""

    name: str
    summary: str
    role: Role
    order: int
    module: str
    solid: Callable[[Example], BoolGrid] | None = None
    model_input: Callable[[Example], npt.NDArray[Any]] | None = None
    from_cad: Callable[[Example, CaptureCad], BoolGrid] | None = None
    config: str = ""  # "module:Class" of a learned method's config
    defaults: Mapping[str, Any] = field(default_factory=dict)
    # How the tables a person reads name it, where not by its name (the files keep the name).
    display: str = ""

    @property
    def label(self) -> str:
        return self.display or self.name

    def __post_init__(self) -> None:
        given = [h for h in (self.solid, self.model_input, self.from_cad) if h is not None]
        if len(given) != 1:
            raise ValueError(f"completion method {self.name!r}: give exactly one of solid "
                             "(no learning), from_cad (the library's CAD) and model_input (a "
                             "checkpoint's network)")

    @property
    def learned(self) -> bool:
        """Whether it runs from a checkpoint (trained by ``mateqa train completion``)."""
        return self.model_input is not None

    def make_config(self, **overrides: Any) -> Any:
        """The network's config: this method's defaults, then ``overrides``.

        Raises:
            ValueError: a method without learning, or a field its config does not have.
        """
        if not self.learned:
            raise ValueError(f"{self.name} has no network to configure")
        module, _, cls = self.config.partition(":")
        kind = getattr(importlib.import_module(module), cls)
        try:
            return kind(**{**self.defaults, **overrides})
        except TypeError as exc:
            raise ValueError(f"bad field for {self.name}: {exc}") from exc


COMPLETIONS: Registry[CompletionMethod] = Registry("completion method", __name__)


def ours() -> CompletionMethod:
    """The completion method the product ships (its role is ``ours``)."""
    (method,) = [m for m in COMPLETIONS.entries() if m.role is Role.OURS]
    return method


def learned() -> tuple[str, ...]:
    """The names of the methods that run from checkpoints, in the registry's order."""
    return tuple(m.name for m in COMPLETIONS.entries() if m.learned)
