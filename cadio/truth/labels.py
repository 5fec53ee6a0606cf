"""The ten relations of every ordered pair of a set of placed parts: the one truth function.

A pair scene, a whole assembly as placed in its file and a training corpus's scenes all go
through ``label_placed``: each part is described once in its own frame (``part_model``: its
features, planar faces and axis lines, and on first use a coarse mesh) and placed by a 4x4 pose;
the face mates of the placed set (``cadio.truth.facemates``) decide coincident and concentric,
the dominant plane directions parallel and perpendicular, the centroids the directional
relations (``cadio.truth.relations.relate``). The assemblies' mates tables are built on the
same result (``cadio.truth.mates``), so a scene and an assembly mean the same thing by each
relation.

Speed: parts whose boxes, enlarged beyond the loosened tolerances, do not meet need no face
work at all (most scenes: parts placed apart); the others pay for their candidate faces' exact
distances and overlaps. ``bench/speed/labels.py`` measures pairs per second.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from OCP.TopoDS import TopoDS_Shape

from cadio.records import Features, FloatArray
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.contact import PartGeometry, describe_shape
from cadio.truth.facemates import FaceMates, find_face_mates
from cadio.truth.proximity import PartModel, ProxyCache
from cadio.truth.relations import (
    CAD_VIEW_AXIS,
    DEFAULT_MARGINS,
    BoundaryMargins,
    RelationResult,
    Vector3,
    relate,
)

__all__ = ["PartModel", "PlacedLabels", "label_placed", "part_model"]


def part_model(shape: TopoDS_Shape, part_id: str, tol: Tolerances = DEFAULT_TOLERANCES,
               features: Features | None = None, *, name: str = "",
               path: str = "") -> PartModel:
    """A part described once in its own frame, ready to be placed in any number of sets.

    Args:
        shape: the solid in the part's own frame, mm.
        part_id: its id; name, path: how the mates table names it.
        tol: the tolerances (features, axis lines).
        features: its features in the same frame where already known (the workspace's
            ``features/<part_id>.json`` of the same shape): the costliest part otherwise.
    """
    return PartModel(describe_shape(shape, part_id, tol, features, name=name, path=path))


@dataclass(frozen=True)
class PlacedLabels:
    """The truth of a placed set of parts.

    parts: each part as placed (``index`` = its position); face_mates: the face-mate
    candidates and each pair's answer; proxies: the parts' contact proxies (built where the
    face mates needed them); seconds: wall time per phase (place, face_mates, relations).
    """

    parts: tuple[PartGeometry, ...]
    face_mates: FaceMates
    proxies: ProxyCache
    view_axis: tuple[float, float, float]
    tolerances: Tolerances
    margins: BoundaryMargins
    seconds: dict[str, float]
    _results: dict[tuple[int, int], RelationResult] = field(default_factory=dict, repr=False)

    def relation(self, i: int, j: int) -> RelationResult:
        """The ten relations of the ordered pair (part i, part j), i != j."""
        if i == j:
            raise ValueError(f"a part is not paired with itself (index {i})")
        if (i, j) not in self._results:
            self._results[(i, j)] = relate(
                self.parts[i].features, self.parts[j].features, self.view_axis,
                self.tolerances, self.face_mates.contact(i, j), self.margins)
        return self._results[(i, j)]

    def ordered_pairs(self) -> list[tuple[int, int]]:
        """Every ordered pair (i, j), i != j, in order."""
        n = len(self.parts)
        return [(i, j) for i in range(n) for j in range(n) if i != j]


def label_placed(models: Sequence[PartModel], poses: Sequence[FloatArray],
                 view_axis: Vector3 = CAD_VIEW_AXIS, tol: Tolerances = DEFAULT_TOLERANCES,
                 margins: BoundaryMargins = DEFAULT_MARGINS) -> PlacedLabels:
    """The ten relations of every ordered pair of placed parts (computed on first ask), with
    the face mates that decided coincident and concentric.

    Args:
        models: the parts, each in its own frame (``part_model``); one model may be placed
            several times (two instances of a part are two parts here).
        poses: (4, 4) float64 part -> world, mm, one per model.
        view_axis: (3,) the observer's forward direction (+Y for CAD without a camera).
        tol: the tolerances; margins: what counts as near a tolerance.

    Returns:
        ``PlacedLabels``; ``.relation(i, j)`` is the ``RelationResult`` of (part i, part j).

    Raises:
        ValueError: poses and models differ in number, or a pose is not a finite 4x4.
    """
    if len(models) != len(poses):
        raise ValueError(f"{len(models)} parts but {len(poses)} poses")
    start = time.perf_counter()
    placed = [np.asarray(p, dtype=np.float64) for p in poses]
    if any(p.shape != (4, 4) or not np.isfinite(p).all() for p in placed):
        raise ValueError("every pose must be a finite (4, 4) matrix")
    parts = tuple(m.part.placed(pose, k) for k, (m, pose) in enumerate(zip(models, placed,
                                                                           strict=True)))
    proxies = ProxyCache(parts, list(zip(models, placed, strict=True)))
    seconds = {"place": time.perf_counter() - start}
    start = time.perf_counter()
    face = find_face_mates(parts, proxies, tol, margins)
    seconds["face_mates"] = time.perf_counter() - start
    axis = (float(view_axis[0]), float(view_axis[1]), float(view_axis[2]))
    return PlacedLabels(parts, face, proxies, axis, tol, margins, seconds)
