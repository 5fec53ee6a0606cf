"""Planted defects: an assembly's variants with parts moved off their mates, or left out.

From an assembly as designed, each variant moves a few parts (never two that share a mate, so
that each defect is found on its own) by one kind and size of defect:

- ``shift``: along a direction the part's mate constrains (across a concentric mate's axis,
  along a coincident mate's normal), by 1, 2 or 5 mm;
- ``turn``: about an axis through its centroid that is no symmetry axis of it (across a
  revolved part's axis), by 2 or 5 degrees;
- ``missing``: the part left out.

Everything is drawn from a seed and written down (``Defect``), so a night lists what it planted
and the scores read it; the inspection never does.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd

from cadio.inspect.symmetry import Symmetry
from cadio.records import FloatArray

SHIFT, TURN, MISSING = "shift", "turn", "missing"
KINDS = (SHIFT, TURN, MISSING)


@dataclass(frozen=True)
class DefectPlan:
    """Which defects to plant: the sizes of each kind, and how many parts per variant."""

    shifts_mm: tuple[float, ...] = (1.0, 2.0, 5.0)
    turns_deg: tuple[float, ...] = (2.0, 5.0)
    missing: bool = True
    parts_per_variant: int = 3
    seed: int = 0

    def kinds(self) -> list[tuple[str, float]]:
        """(kind, size) of every variant, in order."""
        return [*((SHIFT, s) for s in self.shifts_mm), *((TURN, t) for t in self.turns_deg),
                *([(MISSING, 0.0)] if self.missing else [])]


@dataclass(frozen=True)
class Defect:
    """One planted defect: the part (its index), the kind, the size (mm or degrees) and the
    direction (a shift's, or a turn's axis; world = assembly frame), the mate it breaks."""

    index: int
    kind: str
    size: float
    direction: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mate: str = ""

    def motion(self, centre: FloatArray) -> FloatArray:
        """(4, 4) the defect's motion of the part (assembly frame, mm)."""
        out = np.eye(4)
        d = np.array(self.direction)
        if self.kind == SHIFT:
            out[:3, 3] = self.size * d
        elif self.kind == TURN:
            k = d / np.linalg.norm(d)
            kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
            a = math.radians(self.size)
            rot = np.eye(3) + math.sin(a) * kx + (1 - math.cos(a)) * kx @ kx
            out[:3, :3] = rot
            out[:3, 3] = centre - rot @ centre
        return out


@dataclass(frozen=True)
class Variant:
    """An assembly as captured: ``intact`` or one kind and size of defect on a few parts."""

    assembly: str
    name: str
    defects: tuple[Defect, ...] = ()

    def poses(self, design: Sequence[FloatArray], centres: Sequence[FloatArray]
              ) -> dict[int, FloatArray]:
        """Each present part's pose as captured (part -> assembly, mm)."""
        moved = {d.index: d for d in self.defects}
        out = {}
        for i, pose in enumerate(design):
            defect = moved.get(i)
            if defect is None:
                out[i] = pose
            elif defect.kind != MISSING:
                out[i] = defect.motion(centres[i]) @ pose
        return out


def plan_variants(assembly: str, mates: pd.DataFrame, symmetries: Sequence[Symmetry],
                  centres: Sequence[FloatArray], eligible: Sequence[int],
                  plan: DefectPlan = DefectPlan()) -> list[Variant]:
    """The intact assembly and one variant per kind and size of ``plan``, each moving up to
    ``parts_per_variant`` of the ``eligible`` parts (ones with a concentric or coincident
    face mate), no two of which share a mate; seeded by the plan's seed and the assembly."""
    face = mates[(mates["level"] == "face")
                 & mates["relation"].isin(["concentric", "coincident"])]
    mates_of = _mates_of(face)
    candidates = [i for i in eligible if i in mates_of]
    out = [Variant(assembly, "intact")]
    for k, (kind, size) in enumerate(plan.kinds()):
        seed = [plan.seed, k, *(ord(c) for c in assembly[:16])]
        rng = np.random.default_rng(seed)
        chosen = _apart(rng.permutation(candidates).tolist(), mates_of, plan.parts_per_variant)
        defects = tuple(_defect(i, kind, size, mates_of[i], symmetries[i], centres[i], rng)
                        for i in chosen)
        label = f"{kind}-{size:g}{'mm' if kind == SHIFT else 'deg' if kind == TURN else ''}"
        out.append(Variant(assembly, label.rstrip("-0") if kind == MISSING else label, defects))
    return out


def _mates_of(face: pd.DataFrame) -> dict[int, list[Mapping[str, object]]]:
    out: dict[int, list[Mapping[str, object]]] = {}
    for row in face.to_dict("records"):
        out.setdefault(int(row["index_a"]), []).append(row)
        out.setdefault(int(row["index_b"]), []).append(row)
    return out


def _apart(order: list[int], mates_of: Mapping[int, list[Mapping[str, object]]], n: int
           ) -> list[int]:
    """Up to n parts of ``order``, no two sharing a mate."""
    chosen: list[int] = []
    for i in order:
        partners = {int(r["index_a"]) for r in mates_of[i]} | {int(r["index_b"])  # type: ignore[call-overload]
                                                               for r in mates_of[i]}
        if not any(c in partners for c in chosen):
            chosen.append(i)
        if len(chosen) == n:
            break
    return chosen


def _defect(index: int, kind: str, size: float, mates: Sequence[Mapping[str, object]],
            symmetry: Symmetry, centre: FloatArray, rng: np.random.Generator) -> Defect:
    mate = mates[int(rng.integers(len(mates)))]
    axis = np.array(mate["axis"], dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    label = f"{mate['relation']} {mate['index_a']}/{mate['face_a']}-{mate['index_b']}/" \
            f"{mate['face_b']}"
    if kind == SHIFT:
        direction = axis * rng.choice([-1.0, 1.0]) if mate["relation"] == "coincident" else \
            _across(axis, rng)
        return Defect(index, kind, size, _tuple(direction), label)
    if kind == TURN:
        about = np.array(symmetry.axis) if symmetry.axis is not None else axis
        return Defect(index, kind, size, _tuple(_across(about, rng)), label)
    return Defect(index, MISSING, 0.0, mate=label)


def _across(axis: FloatArray, rng: np.random.Generator) -> FloatArray:
    """A unit vector across ``axis``, at a random angle about it."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    t = rng.uniform(0, 2 * math.pi)
    out: FloatArray = math.cos(t) * u + math.sin(t) * v
    return out


def _tuple(v: FloatArray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


def defects_frame(variants: Sequence[Variant]) -> pd.DataFrame:
    """One row per planted defect (assembly, variant, index, kind, size, direction, mate)."""
    rows = [{"assembly": v.assembly, "variant": v.name, **asdict(d)}
            for v in variants for d in v.defects]
    return pd.DataFrame(rows, columns=["assembly", "variant", "index", "kind", "size",
                                       "direction", "mate"])
