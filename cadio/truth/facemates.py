"""Face-level mates of a set of placed parts, and what they say about each pair.

One computation serves the assemblies' mates tables and the part relations of scenes and
assemblies alike (DESIGN.md, "Relations"):

- coincident: planar faces of two parts with opposite outward normals (within
  ``mate_angle_deg``), planes within ``contact_mm``, and an overlap of more than
  ``min_overlap_mm2`` (a Boolean common of the two faces laid on one plane, with the fuzzy value
  ``overlap_fuzzy_mm``; touching along an edge is no mate);
- concentric: cylinder or cone faces of two parts on coaxial lines (``coaxial_deg``,
  ``coaxial_mm``) whose faces lie within ``concentric_gap_mm`` of each other (exact distance).

Candidates are gathered at tolerances loosened by the boundary margins
(``relations.loose_tolerances``), so the same pass tells which answers sit near a tolerance:
an answer is near when it differs between the loosened and the tightened tolerances.

Pruning cannot change under a rigid motion of the whole set: boxes enlarged beyond the
tolerances skip only pairs that cannot meet, concentric candidates come from matching axis lines
(a test on lines), and each coaxial face pair is ruled out only where a lower bound on its
distance exceeds the limit (face boxes, then the faces' extents along and around the axis from
a coarse mesh with its slack) and measured exactly (BRepExtrema) otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from cadio.records import FloatArray
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.contact import SLACK, AxisFace, AxisLine, PartGeometry, face_overlap
from cadio.truth.proximity import ProxyCache, box_distances, box_pairs, close_faces, coaxial_bound
from cadio.truth.relations import (
    DEFAULT_MARGINS,
    BoundaryMargins,
    PairContact,
    loose_tolerances,
    tight_tolerances,
)


@dataclass(frozen=True)
class Coincident:
    """Two opposed planar faces of parts a < b (set indices) that overlap: a coincident mate
    where ``within`` the tolerances. normal: a's outward normal; centre: the overlap's centroid
    (mm); angle_deg: between the normals and exact opposition; offset_mm: between the planes."""

    a: int
    b: int
    face_a: int
    face_b: int
    angle_deg: float
    offset_mm: float
    area_mm2: float
    normal: FloatArray
    centre: FloatArray

    def within(self, tol: Tolerances) -> bool:
        return (self.angle_deg <= tol.mate_angle_deg + SLACK
                and self.offset_mm <= tol.contact_mm + SLACK)


@dataclass(frozen=True)
class Coaxial:
    """Two coaxial faces of parts a < b on their axis lines; the lines' angle (deg) and gap (mm)."""

    a: PartGeometry
    line_a: AxisLine
    face_a: AxisFace
    b: PartGeometry
    line_b: AxisLine
    face_b: AxisFace
    angle_deg: float
    gap_mm: float


@dataclass(frozen=True)
class Concentric:
    """Two coaxial faces ``distance_mm`` apart (exact): a concentric mate where ``within``."""

    coaxial: Coaxial
    distance_mm: float

    @property
    def pair(self) -> tuple[int, int]:
        return self.coaxial.a.index, self.coaxial.b.index

    def within(self, tol: Tolerances) -> bool:
        c = self.coaxial
        return (c.angle_deg <= tol.coaxial_deg + SLACK and c.gap_mm <= tol.coaxial_mm + SLACK
                and self.distance_mm <= tol.concentric_gap_mm * (1.0 + SLACK))


@dataclass(frozen=True)
class FaceMates:
    """The face-mate candidates of a set of parts within the loosened tolerances, and what they
    say of each pair (``contacts``: (i, j), i < j -> answer, for every pair with a candidate;
    any other pair has none)."""

    coincident: tuple[Coincident, ...]
    concentric: tuple[Concentric, ...]
    contacts: dict[tuple[int, int], PairContact]
    tolerances: Tolerances

    def mates(self) -> tuple[list[Coincident], list[Concentric]]:
        """The coincident and concentric face mates (within the tolerances)."""
        tol = self.tolerances
        return ([c for c in self.coincident if c.within(tol)],
                [c for c in self.concentric if c.within(tol)])

    def contact(self, i: int, j: int) -> PairContact:
        """The face mates' answer for parts i and j (either order)."""
        return self.contacts.get((min(i, j), max(i, j)), PairContact())


def find_face_mates(parts: Sequence[PartGeometry], proxies: ProxyCache,
                    tol: Tolerances = DEFAULT_TOLERANCES,
                    margins: BoundaryMargins = DEFAULT_MARGINS) -> FaceMates:
    """Face-mate candidates of every pair of parts, within the loosened tolerances.

    Args:
        parts: the parts as placed, ``index`` = their position in the sequence.
        proxies: their contact proxies (``ProxyCache``).
        tol: the tolerances of the mates; margins: how far beyond them a candidate is kept.
    """
    loose = loose_tolerances(tol, margins)
    concentric = _concentric(parts, proxies, loose)
    coincident = [c for i, j in box_pairs(parts, 2.0 * loose.contact_mm)
                  for c in _coincident(parts[i], parts[j], loose)]
    answers = _answers(coincident, concentric, tol, tight_tolerances(tol, margins))
    return FaceMates(tuple(coincident), tuple(concentric), answers, tol)


def _answers(coincident: Sequence[Coincident], concentric: Sequence[Concentric],
             tol: Tolerances, tight: Tolerances) -> dict[tuple[int, int], PairContact]:
    """Per pair with candidates: the answers at ``tol``, near where the loosened answer (any
    candidate) differs from the tightened one."""
    flat: dict[tuple[int, int], list[Coincident]] = {}
    axial: dict[tuple[int, int], list[Concentric]] = {}
    for c in coincident:
        flat.setdefault((c.a, c.b), []).append(c)
    for k in concentric:
        axial.setdefault(k.pair, []).append(k)
    out = {}
    for pair in sorted(set(flat) | set(axial)):
        fs, ks = flat.get(pair, []), axial.get(pair, [])
        out[pair] = PairContact(
            coincident=any(c.within(tol) for c in fs),
            concentric=any(k.within(tol) for k in ks),
            coincident_near=bool(fs) and not any(c.within(tight) for c in fs),
            concentric_near=bool(ks) and not any(k.within(tight) for k in ks),
            coincident_gap_mm=min((c.offset_mm for c in fs), default=math.nan),
            concentric_gap_mm=min((k.distance_mm for k in ks), default=math.nan))
    return out


# ---------------------------------------------------------------- coincident


def _coincident(a: PartGeometry, b: PartGeometry, tol: Tolerances) -> list[Coincident]:
    """Planar faces of two parts face to face within ``tol`` that overlap."""
    if not len(a.plane_ids) or not len(b.plane_ids):
        return []
    cos = a.normals @ b.normals.T  # (ka, kb)
    opposed = cos <= -math.cos(math.radians(tol.mate_angle_deg)) + SLACK
    rel = b.centres[None, :, :] - a.centres[:, None, :]  # (ka, kb, 3)
    along = np.einsum("ijk,ik->ij", rel, a.normals)
    offset = np.maximum(np.abs(along), np.abs(np.einsum("ijk,jk->ij", rel, b.normals)))
    inplane = np.linalg.norm(rel - along[..., None] * a.normals[:, None, :], axis=2)
    near = inplane <= a.reach[:, None] + b.reach[None, :] + tol.contact_mm
    out = []
    for k, m in zip(*np.nonzero(opposed & (offset <= tol.contact_mm + SLACK) & near),
                    strict=True):
        area, centre = face_overlap(a.faces[a.plane_ids[k]], b.faces[b.plane_ids[m]],
                                    a.normals[k], a.centres[k], b.normals[m], b.centres[m],
                                    tol.overlap_fuzzy_mm)
        if area > tol.min_overlap_mm2:
            angle = math.degrees(math.acos(min(1.0, -float(cos[k, m]))))
            out.append(Coincident(a.index, b.index, a.plane_ids[k], b.plane_ids[m], angle,
                                  float(offset[k, m]), area, a.normals[k], centre))
    return out


# ---------------------------------------------------------------- concentric


def _concentric(parts: Sequence[PartGeometry], proxies: ProxyCache,
                tol: Tolerances) -> list[Concentric]:
    """Every pair of coaxial faces of two parts within ``concentric_gap_mm`` (exact)."""
    by_pair: dict[tuple[int, int], list[Coaxial]] = {}
    for c in _coaxial_faces(parts, tol):
        by_pair.setdefault((c.a.index, c.b.index), []).append(c)
    out = []
    for (i, j), found in sorted(by_pair.items()):
        near = [c for c in found if _may_be_near(c, proxies, tol.concentric_gap_mm)]
        if not near:
            continue
        ids = [(c.face_a.face_id, c.face_b.face_id) for c in near]
        dist = close_faces(proxies[i], proxies[j], ids, tol.concentric_gap_mm)
        out += [Concentric(c, dist[key]) for c, key in zip(near, ids, strict=True)
                if key in dist]
    return out


def _coaxial_faces(parts: Sequence[PartGeometry], tol: Tolerances) -> Iterator[Coaxial]:
    """Every pair of faces on coaxial axis lines of two parts (lines within ``coaxial_deg`` and
    ``coaxial_mm``), part a before part b; line pairs in order of the lines."""
    owner = [(p.index, k) for p in parts for k in range(len(p.lines))]
    if len(owner) < 2:
        return
    lines = [parts[i].lines[k] for i, k in owner]
    d = np.array([ln.direction for ln in lines])
    mid = np.array([ln.mid for ln in lines])
    part_of = np.array([i for i, _ in owner])
    for m, n in _coaxial_lines(d, mid, part_of, tol):
        angle, gap = _line_pair(d[m], mid[m], d[n], mid[n])
        (pa, la), (pb, lb) = sorted([(parts[part_of[m]], lines[m]),
                                     (parts[part_of[n]], lines[n])], key=lambda pl: pl[0].index)
        for fa in la.faces:
            for fb in lb.faces:
                yield Coaxial(pa, la, fa, pb, lb, fb, angle, gap)


def _coaxial_lines(d: FloatArray, mid: FloatArray, part_of: np.ndarray, tol: Tolerances,
                   block: int = 256) -> Iterator[tuple[int, int]]:
    """Index pairs m < n of lines of different parts within the tolerances, in order; all
    pairs at once, a block of rows at a time (memory grows with block x lines)."""
    for start in range(0, len(d) - 1, block):
        rows = np.arange(start, min(start + block, len(d) - 1))
        angle, gap = _line_pair(d[rows, None, :], mid[rows, None, :], d[None], mid[None])
        keep = ((np.arange(len(d))[None, :] > rows[:, None])
                & (part_of[None, :] != part_of[rows, None])
                & (angle <= tol.coaxial_deg + SLACK) & (gap <= tol.coaxial_mm + SLACK))
        for m, n in zip(*np.nonzero(keep), strict=True):
            yield int(rows[m]), int(n)


def _line_pair(dm: FloatArray, pm: FloatArray, dn: FloatArray, pn: FloatArray
               ) -> tuple[Any, Any]:
    """Angle (degrees) between lines (direction, point) and the larger distance of either
    point from the other line (mm), broadcast over leading axes."""
    cross = np.linalg.norm(np.cross(dm, dn), axis=-1)
    dot = np.einsum("...k,...k->...", dm, dn)
    angle = np.degrees(np.arctan2(cross, np.abs(dot)))
    rel = pn - pm
    gap_n = np.linalg.norm(rel - np.einsum("...k,...k->...", rel, dm)[..., None] * dm, axis=-1)
    gap_m = np.linalg.norm(rel - np.einsum("...k,...k->...", rel, dn)[..., None] * dn, axis=-1)
    if np.ndim(angle) == 0:
        return float(angle), float(max(gap_m, gap_n))
    return angle, np.maximum(gap_m, gap_n)


def _may_be_near(c: Coaxial, proxies: ProxyCache, limit_mm: float) -> bool:
    """False when lower bounds put the two faces more than ``limit_mm`` apart: their boxes
    (no mesh needed), then their extents along and around a's axis (a coarse mesh)."""
    i, j = c.a.index, c.b.index
    if box_distances(proxies.boxes(i)[c.face_a.face_id],
                     proxies.boxes(j)[c.face_b.face_id]) > limit_mm:
        return False
    bound = coaxial_bound(proxies[i], c.face_a.face_id, proxies[j], c.face_b.face_id,
                          c.line_a.mid, c.line_a.direction)
    return bound <= limit_mm
