"""Ground-truth mates of a CAD assembly: face-level mates, part-level relations and joints.

For every pair of parts (solids already in the assembly frame, mm), one table with ONE ROW PER
MATE, RELATION OR JOINT (``COLUMNS``, schema in ``write_mates``), for index_a < index_b, read
"a <relation> b":

- level "face": ``concentric``, one row per pair of coaxial cylindrical/conical faces (axes
  within ``coaxial_deg``, lines within ``coaxial_mm``) whose faces lie within
  ``concentric_gap_mm`` of each other (exact face-to-face distance): ``fit`` says "fit" when the
  radii agree within ``fit_radius_mm`` (cones: semi-angles within ``mate_angle_deg`` and radii
  within ``fit_radius_mm`` at a common axial station) and "clearance" otherwise (a gland beside a
  shaft across fillets, a bolt in a clearance hole; a cylinder against a cone). ``coincident``
  between planar faces with opposite outward normals (within ``mate_angle_deg``), planes within
  ``contact_mm`` and an overlap of more than ``min_overlap_mm2`` (a Boolean common of the two
  faces laid on one plane, with the fuzzy value ``overlap_fuzzy_mm`` so that exactly touching
  faces do not come out with nothing in common; touching along an edge is no mate). Pairs in
  contact also get ``parallel``/``perpendicular`` rows for their largest principal faces.
- level "part": the ten relations of ``cadio.truth.relations.relate`` (view axis +Y for CAD);
  the part-level ``concentric`` needs no contact (principal axes coaxial).
- level "joint": the joint a CAD user would set, derived from the pair's coincident contacts and
  shafts in bores (``cadio.truth.joints``): ``relation`` is the suggested joint, ``kinematic``
  the pure degree-of-freedom one, with Onshape / FreeCAD / Fusion 360 names.

Pruning (``cadio.truth.contact``) cannot change under a rigid motion of the whole assembly.
Coincident mates need contact: boxes enlarged by twice ``contact_mm`` skip only pairs that
cannot touch, and the mate test itself is exact; pairs "in contact" are within ``contact_mm``
(exact B-rep distance). Concentric candidates come from matching the axis lines of all parts (a
test on lines, invariant by construction); each coaxial face pair is then ruled out where a
lower bound on its distance exceeds ``concentric_gap_mm`` (face boxes, then the faces' extents
along and around the axis from a coarse mesh with its slack: both hold in any frame) and
measured exactly (BRepExtrema) otherwise.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cadio.cad.faces import CYLINDER
from cadio.cad.step import StepSolid, read_step
from cadio.records import DIRECTIONAL, Features, Relation
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.contact import (
    SLACK,
    AxisFace,
    AxisLine,
    PartGeometry,
    ProxyCache,
    box_distances,
    box_pairs,
    close_faces,
    coaxial_bound,
    contact_pairs,
    describe_part,
    face_overlap,
)
from cadio.truth.joints import AXIS, Constraint, derive_joint
from cadio.truth.joints import PLANE as PLANE_CONTACT
from cadio.truth.relations import CAD_VIEW_AXIS, RelationResult, relate
from cadio.workspace import atomic_path

COLUMNS = (
    "assembly", "part_a", "part_b", "index_a", "index_b", "name_a", "name_b", "path_a", "path_b",
    "level", "relation", "face_a", "face_b", "axis", "origin", "distance_mm", "angle_deg",
    "overlap_area_mm2", "radial_gap_mm", "fit", "kinematic", "dof", "onshape", "freecad",
    "fusion360", "evidence",
)
LEVELS = ("face", "part", "joint")
Row = dict[str, Any]  # one table row, keys ``COLUMNS``
FIT, CLEARANCE = "fit", "clearance"


@dataclass(frozen=True)
class _FaceMate:
    """A face-level mate: its row, the kinematic constraints it sets (a planar contact, a shaft
    in a bore, a seated cone), and whether its faces are known to be within ``contact_mm``."""

    row: Row
    constraints: tuple[Constraint, ...]
    touching: bool


@dataclass(frozen=True)
class MatesResult:
    """Mates of one assembly.

    table: one row per mate, relation or joint, columns ``COLUMNS``; ``table.attrs`` holds the
    tolerances and view axis. n_pairs: all unordered pairs of parts; n_box_pairs: pairs
    passing the box filter; n_contact_pairs: pairs within ``contact_mm`` (exact distance).
    seconds: wall time per phase: features, prune (boxes and exact contact), face_mates,
    relations, joints; read when the result came from a file.
    """

    table: pd.DataFrame
    n_parts: int
    n_pairs: int
    n_box_pairs: int
    n_contact_pairs: int
    seconds: dict[str, float] = field(default_factory=dict)

    def level(self, level: str) -> pd.DataFrame:
        """The rows of one level: "face", "part" or "joint"."""
        return self.table[self.table["level"] == level].reset_index(drop=True)


def extract_mates(
    solids: Sequence[StepSolid],
    tol: Tolerances = DEFAULT_TOLERANCES,
    view_axis: Sequence[float] = CAD_VIEW_AXIS,
    *,
    assembly: str = "",
    part_ids: Mapping[int, str] | None = None,
) -> MatesResult:
    """Face-level mates, part-level relations and joints of every pair of parts.

    Args:
        solids: the assembly's solids, in the assembly frame (mm), as ``read_step`` returns them.
        tol: the tolerances (mate angle, contact, coaxial, concentric gap, fit radius,
            parallel, freeform fit, smallest overlap area and its fuzzy value).
        view_axis: (3,) the observer's forward direction for left/right/front/behind (+Y for CAD).
        assembly: the assembly name written in every row.
        part_ids: solid index -> part id (default: the index as text).

    Returns:
        A ``MatesResult``: the table (no file is touched), pair counts and seconds per phase.

    Raises:
        GeometryError: a solid has no faces or no volume.
    """
    clock = _Clock()
    ids = part_ids or {}
    parts = [describe_part(s, k, ids.get(s.info.index, str(s.info.index)), tol)
             for k, s in enumerate(solids)]
    clock.lap("features")
    boxed = box_pairs(parts, 2.0 * tol.contact_mm)
    proxies = ProxyCache(parts)
    clock.lap("prune")
    mates = _concentric_mates(parts, proxies, tol)
    mates += [m for i, j in boxed for m in _coincident_mates(parts[i], parts[j], tol)]
    rows = [m.row for m in mates]
    clock.lap("face_mates")
    touching = {(m.row["index_a"], m.row["index_b"]) for m in mates if m.touching}
    contact = contact_pairs(parts, boxed, touching, tol.contact_mm, proxies)
    clock.lap("prune")
    relations = {(i, j): relate(parts[i].features, parts[j].features, view_axis, tol)
                 for i in range(len(parts)) for j in range(i + 1, len(parts))}
    rows += [r for (i, j), rr in relations.items() for r in _part_rows(parts[i], parts[j], rr)]
    rows += [r for i, j in contact
             for r in _principal_face_rows(parts[i], parts[j], relations[(i, j)])]
    clock.lap("relations")
    rows += _joint_rows(parts, mates, tol)
    clock.lap("joints")
    table = _table(rows, assembly)
    table.attrs = {"tolerances": tol.as_dict(), "view_axis": [float(v) for v in view_axis]}
    n = len(parts)
    return MatesResult(table, n, n * (n - 1) // 2, len(boxed), len(contact), clock.seconds)


def read_assembly_mates(
    path: Path | str,
    tol: Tolerances = DEFAULT_TOLERANCES,
    view_axis: Sequence[float] = CAD_VIEW_AXIS,
    *,
    part_ids: Mapping[int, str] | None = None,
) -> MatesResult:
    """Read a STEP assembly and extract its mates; the assembly is named after the file stem.

    Raises:
        StepReadError: the file cannot be read.
    """
    start = time.perf_counter()
    solids = read_step(Path(path))
    read_s = time.perf_counter() - start
    result = extract_mates(solids, tol, view_axis, assembly=Path(path).stem, part_ids=part_ids)
    result.seconds["read"] = read_s
    return result


def write_mates(path: Path | str, table: pd.DataFrame) -> None:
    """Write a mates table to parquet (``Workspace.mates(assembly)``), atomically.

    Schema: assembly, part_a, part_b (ids), index_a < index_b (solid indices), name_*, path_*
    (instance paths), level ("face", "part", "joint"), relation (concentric, coincident,
    parallel, perpendicular, left ... behind; for joints the suggested joint), face_a, face_b
    (face ids, -1 when none), axis, origin (3 floats, assembly frame, or None), distance_mm
    (coincident: plane offset; concentric: distance between the axis lines), angle_deg,
    overlap_area_mm2, radial_gap_mm (concentric: difference of the radii at the common axial
    station; NaN when not applicable), fit ("fit" or "clearance" for concentric), kinematic,
    dof (-1 when none), onshape, freecad, fusion360 (joint names), evidence (text).
    ``table.attrs`` (tolerances, view axis) go in the metadata.
    """
    with atomic_path(Path(path)) as tmp:
        table.to_parquet(tmp, index=False)


def read_mates(path: Path | str) -> pd.DataFrame:
    """Read a mates table written by ``write_mates``."""
    return pd.read_parquet(Path(path))


# ---------------------------------------------------------------- concentric


@dataclass(frozen=True)
class _Coaxial:
    """Two coaxial faces of parts a < b on their axis lines; the lines' angle (deg) and gap (mm)."""

    a: PartGeometry
    line_a: AxisLine
    face_a: AxisFace
    b: PartGeometry
    line_b: AxisLine
    face_b: AxisFace
    angle_deg: float
    gap_mm: float


def _concentric_mates(parts: list[PartGeometry], proxies: ProxyCache,
                      tol: Tolerances) -> list[_FaceMate]:
    """One mate per pair of coaxial faces of two parts within ``concentric_gap_mm`` (exact)."""
    by_pair: dict[tuple[int, int], list[_Coaxial]] = {}
    for c in _coaxial_faces(parts, tol):
        by_pair.setdefault((c.a.index, c.b.index), []).append(c)
    mates = []
    for (i, j), found in sorted(by_pair.items()):
        near = [c for c in found if _may_be_near(c, proxies, tol.concentric_gap_mm)]
        if not near:
            continue
        ids = [(c.face_a.face_id, c.face_b.face_id) for c in near]
        dist = close_faces(proxies[i], proxies[j], ids, tol.concentric_gap_mm)
        mates += [_concentric_mate(c, dist[key], tol)
                  for c, key in zip(near, ids, strict=True) if key in dist]
    return mates


def _coaxial_faces(parts: list[PartGeometry], tol: Tolerances) -> Iterator[_Coaxial]:
    """Every pair of faces on coaxial axis lines of two parts (lines within ``coaxial_deg`` and
    ``coaxial_mm``), part a before part b."""
    owner = [(p.index, k) for p in parts for k in range(len(p.lines))]
    if len(owner) < 2:
        return
    lines = [parts[i].lines[k] for i, k in owner]
    d = np.array([ln.direction for ln in lines])
    mid = np.array([ln.mid for ln in lines])
    part_of = np.array([i for i, _ in owner])
    for m in range(len(lines) - 1):
        n = np.arange(m + 1, len(lines))
        cross = np.linalg.norm(np.cross(d[m], d[n]), axis=1)
        angle = np.degrees(np.arctan2(cross, np.abs(d[n] @ d[m])))
        rel = mid[n] - mid[m]
        gap_n = np.linalg.norm(rel - np.outer(rel @ d[m], d[m]), axis=1)
        gap_m = np.linalg.norm(rel - (np.einsum("ij,ij->i", rel, d[n]))[:, None] * d[n], axis=1)
        gap = np.maximum(gap_m, gap_n)
        keep = ((part_of[n] != part_of[m]) & (angle <= tol.coaxial_deg + SLACK)
                & (gap <= tol.coaxial_mm + SLACK))
        for k in np.nonzero(keep)[0]:
            (pa, la), (pb, lb) = sorted([(parts[part_of[m]], lines[m]),
                                         (parts[part_of[n[k]]], lines[n[k]])],
                                        key=lambda pl: pl[0].index)
            for fa in la.faces:
                for fb in lb.faces:
                    yield _Coaxial(pa, la, fa, pb, lb, fb, float(angle[k]), float(gap[k]))


def _may_be_near(c: _Coaxial, proxies: ProxyCache, limit_mm: float) -> bool:
    """False when lower bounds put the two faces more than ``limit_mm`` apart: their boxes
    (no mesh needed), then their extents along and around a's axis (a coarse mesh)."""
    i, j = c.a.index, c.b.index
    if box_distances(proxies.boxes(i)[c.face_a.face_id],
                     proxies.boxes(j)[c.face_b.face_id]) > limit_mm:
        return False
    bound = coaxial_bound(proxies[i], c.face_a.face_id, proxies[j], c.face_b.face_id,
                          c.line_a.mid, c.line_a.direction)
    return bound <= limit_mm


def _concentric_mate(c: _Coaxial, distance: float, tol: Tolerances) -> _FaceMate:
    """The mate of two coaxial faces ``distance`` mm apart, read at their common axial station
    (the middle of their overlap along a's axis, or of the gap between their nearest ends)."""
    d = c.line_a.direction
    ta, tb = c.face_a.ends @ d, c.face_b.ends @ d
    lo, hi = max(ta.min(), tb.min()), min(ta.max(), tb.max())
    station = c.line_a.mid + (0.5 * (lo + hi) - float(c.line_a.mid @ d)) * d
    ra, rb = c.face_a.radius_at(station), c.face_b.radius_at(station)
    parallel = _parallel_surfaces(c.face_a, c.face_b, d, tol)
    kind = FIT if parallel and abs(ra - rb) <= tol.fit_radius_mm + SLACK else CLEARANCE
    in_bore = parallel and _shaft_in_bore(c.face_a, ra, c.face_b, rb, hi - lo, tol)
    constraints = _bore_constraints(c.face_a.kind, kind, d, station) if in_bore else ()
    evidence = (f"{kind}: face {c.face_a.face_id} ({_kind(c.face_a)} r={ra:.3f}) and face "
                f"{c.face_b.face_id} ({_kind(c.face_b)} r={rb:.3f}) at their common station, "
                f"{distance:.4f} mm apart, {hi - lo:.3f} mm of axial overlap (< 0: apart)"
                f"{'; a shaft in a bore' if in_bore else ''}")
    row = _row(c.a, c.b, "face", Relation.CONCENTRIC.value, face_a=c.face_a.face_id,
               face_b=c.face_b.face_id, axis=d, origin=station, distance_mm=c.gap_mm,
               angle_deg=c.angle_deg, radial_gap_mm=abs(ra - rb), fit=kind, evidence=evidence)
    return _FaceMate(row, constraints, distance <= tol.contact_mm * (1.0 + SLACK))


def _bore_constraints(surface: str, kind: str, d: np.ndarray, station: np.ndarray
                      ) -> tuple[Constraint, ...]:
    """A shaft in a bore keeps the axis; a cone seated in a cone (a fit) also stops axial
    motion, read both ways as a planar contact is (see ``cadio.truth.joints``)."""
    axis = Constraint(AXIS, d, station)
    if surface == CYLINDER or kind != FIT:
        return (axis,)
    return axis, Constraint(PLANE_CONTACT, d, station)


def _parallel_surfaces(fa: AxisFace, fb: AxisFace, d: np.ndarray, tol: Tolerances) -> bool:
    """Two cylinders, or two cones opening the same way with semi-angles within
    ``mate_angle_deg``: surfaces that stay the same distance apart along the axis."""
    if fa.kind != fb.kind:
        return False
    gap = abs(fa.semi_angle_deg(d) - fb.semi_angle_deg(d))
    return fa.kind == CYLINDER or gap <= tol.mate_angle_deg + SLACK


def _shaft_in_bore(fa: AxisFace, ra: float, fb: AxisFace, rb: float, overlap: float,
                   tol: Tolerances) -> bool:
    """A convex face inside a concave one (radii ra, rb at the common station, within
    ``fit_radius_mm`` of interference), engaged along the axis by more than ``contact_mm``."""
    if fa.convex == fb.convex or overlap <= tol.contact_mm:
        return False
    shaft, bore = (ra, rb) if fa.convex else (rb, ra)
    return bore - shaft >= -tol.fit_radius_mm - SLACK


def _kind(f: AxisFace) -> str:
    return f"{'shaft' if f.convex else 'hole'} {f.kind}"


# ---------------------------------------------------------------- coincident


def _coincident_mates(a: PartGeometry, b: PartGeometry, tol: Tolerances) -> list[_FaceMate]:
    """Planar faces of two parts in contact: opposite normals, planes close, positive overlap."""
    if not len(a.plane_ids) or not len(b.plane_ids):
        return []
    cos = a.normals @ b.normals.T  # (ka, kb)
    opposed = cos <= -math.cos(math.radians(tol.mate_angle_deg)) + SLACK
    rel = b.centres[None, :, :] - a.centres[:, None, :]  # (ka, kb, 3)
    along = np.einsum("ijk,ik->ij", rel, a.normals)
    offset = np.maximum(np.abs(along), np.abs(np.einsum("ijk,jk->ij", rel, b.normals)))
    inplane = np.linalg.norm(rel - along[..., None] * a.normals[:, None, :], axis=2)
    near = inplane <= a.reach[:, None] + b.reach[None, :] + tol.contact_mm
    mates = []
    for k, m in zip(*np.nonzero(opposed & (offset <= tol.contact_mm + SLACK) & near),
                    strict=True):
        area, centre = face_overlap(a.faces[a.plane_ids[k]], b.faces[b.plane_ids[m]],
                                    a.normals[k], a.centres[k], b.normals[m], b.centres[m],
                                    tol.overlap_fuzzy_mm)
        if area <= tol.min_overlap_mm2:
            continue
        angle = math.degrees(math.acos(min(1.0, -float(cos[k, m]))))
        row = _row(
            a, b, "face", Relation.COINCIDENT.value, face_a=a.plane_ids[k],
            face_b=b.plane_ids[m], axis=a.normals[k], origin=centre,
            distance_mm=float(offset[k, m]), angle_deg=angle, overlap_area_mm2=area,
            evidence=f"planar faces {a.plane_ids[k]} / {b.plane_ids[m]} face to face, "
                     f"{offset[k, m]:.4f} mm apart, overlap {area:.3f} mm^2")
        mates.append(_FaceMate(row, (Constraint(PLANE_CONTACT, a.normals[k], centre),), True))
    return mates


# ---------------------------------------------------------------- part level


def _part_rows(a: PartGeometry, b: PartGeometry, rr: RelationResult) -> list[Row]:
    """One row per relation of ``relate`` that holds for (a, b). Face ids stay -1: relate's
    choice among tied coplanar faces is not stable under a rigid motion."""
    rows = []
    for rel in rr.holding():
        dist, angle, evidence = _part_evidence(rel, rr)
        rows.append(_row(a, b, "part", rel.value, distance_mm=dist, angle_deg=angle,
                         evidence=evidence))
    return rows


def _part_evidence(rel: Relation, rr: RelationResult) -> tuple[float, float, str]:
    """(distance mm, angle deg, text) that decided one part-level relation."""
    nan = float("nan")
    if rel in (Relation.PARALLEL, Relation.PERPENDICULAR, Relation.COINCIDENT):
        gap = nan if rr.plane_gap_mm is None else rr.plane_gap_mm
        angle = nan if rr.plane_angle_deg is None else rr.plane_angle_deg
        return gap, angle, f"principal planes {angle:.3f} deg apart, gap {gap:.4f} mm"
    if rel == Relation.CONCENTRIC:
        dist = nan if rr.axis_distance_mm is None else rr.axis_distance_mm
        angle = nan if rr.axis_angle_deg is None else rr.axis_angle_deg
        return dist, angle, f"principal axes {angle:.3f} deg, {dist:.4f} mm apart"
    angle = rr.direction_deg[DIRECTIONAL.index(rel)]
    return rr.centre_distance_mm, angle, f"b to a {angle:.2f} deg off the {rel.value} axis"


def _principal_face_rows(a: PartGeometry, b: PartGeometry, rr: RelationResult) -> list[Row]:
    """Face-level parallel / perpendicular rows for the largest principal faces of parts in
    contact (the part-level truth from ``relate``)."""
    faces = {"face_a": _largest_principal_face(a.features),
             "face_b": _largest_principal_face(b.features)}
    return [_row(a, b, "face", rel.value, angle_deg=rr.plane_angle_deg, **faces,
                 evidence="largest faces of the principal plane directions")
            for rel in (Relation.PARALLEL, Relation.PERPENDICULAR) if rr[rel]]


def _largest_principal_face(f: Features) -> int:
    """Id of the largest face of the principal plane direction (near-ties: smallest id)."""
    principal = f.principal_plane
    if principal is None or not f.planes:
        return -1
    group = max(f.planes, key=lambda g: abs(float(np.dot(g.normal, principal))))
    top = max(group.face_areas)
    return min(i for i, a in zip(group.face_ids, group.face_areas, strict=True)
               if a >= top * (1.0 - 1e-6))


# ---------------------------------------------------------------- joints and the table


def _joint_rows(parts: list[PartGeometry], mates: list[_FaceMate], tol: Tolerances) -> list[Row]:
    """One joint row per pair with at least one coincident contact or shaft in a bore."""
    by_pair: dict[tuple[int, int], list[Constraint]] = {}
    for m in mates:
        if m.constraints:
            by_pair.setdefault((m.row["index_a"], m.row["index_b"]), []).extend(m.constraints)
    out = []
    for (i, j), constraints in sorted(by_pair.items()):
        a, b = parts[i], parts[j]
        joint = derive_joint(constraints, (a.name, b.name), tol)
        assert joint is not None
        n_axis = sum(c.kind == AXIS for c in constraints)
        out.append(_row(
            a, b, "joint", joint.suggested, axis=joint.axis, origin=joint.origin,
            kinematic=joint.kinematic, dof=joint.dof, **joint.cad_names(),
            evidence=f"{joint.reason}; from {len(constraints) - n_axis} planar contacts "
                     f"and {n_axis} shafts in bores"))
    return out


def _row(a: PartGeometry, b: PartGeometry, level: str, relation: str, **values: Any) -> Row:
    row: dict[str, Any] = {
        "part_a": a.part_id, "part_b": b.part_id, "index_a": a.index, "index_b": b.index,
        "name_a": a.name, "name_b": b.name, "path_a": a.path, "path_b": b.path,
        "level": level, "relation": relation, "face_a": -1, "face_b": -1, "axis": None,
        "origin": None, "distance_mm": math.nan, "angle_deg": math.nan,
        "overlap_area_mm2": math.nan, "radial_gap_mm": math.nan, "fit": None,
        "kinematic": None, "dof": -1, "onshape": None, "freecad": None, "fusion360": None,
        "evidence": "",
    }
    row.update(values)
    for key in ("axis", "origin"):
        if row[key] is not None:
            row[key] = [float(v) + 0.0 for v in row[key]]  # no -0.0
    return row


def _table(rows: list[Row], assembly: str) -> pd.DataFrame:
    table = pd.DataFrame(rows, columns=list(COLUMNS))
    table["assembly"] = assembly
    for col in ("index_a", "index_b", "face_a", "face_b", "dof"):
        table[col] = table[col].astype("int64")
    for col in ("distance_mm", "angle_deg", "overlap_area_mm2", "radial_gap_mm"):
        table[col] = table[col].astype("float64")
    table["_level"] = table["level"].map(LEVELS.index)
    table = table.sort_values(["index_a", "index_b", "_level", "relation", "face_a", "face_b"])
    return table.drop(columns="_level").reset_index(drop=True)


class _Clock:
    """Seconds per phase."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, phase: str) -> None:
        now = time.perf_counter()
        self.seconds[phase] = self.seconds.get(phase, 0.0) + now - self._last
        self._last = now
