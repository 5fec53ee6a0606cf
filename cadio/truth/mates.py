"""Ground-truth mates of a CAD assembly: face-level mates, part-level relations and joints.

For every pair of parts (solids already in the assembly frame, mm), one table with ONE ROW PER
MATE, RELATION OR JOINT (``COLUMNS``, schema in ``write_mates``), for index_a < index_b, read
"a <relation> b":

- level "face": ``concentric`` between coaxial cylindrical/conical faces (axes within
  ``coaxial_deg``, lines within ``coaxial_mm``, overlapping along the axis or abutting within
  ``contact_mm``, any radii; ``fit`` says "fit" for a shaft in a bore with at most
  ``fit_clearance_mm`` of radial clearance, "nested" for a larger gap, "aligned" for two holes or
  two shafts), and ``coincident`` between planar faces with opposite outward normals (within
  ``mate_angle_deg``), planes within ``contact_mm`` and an overlap of more than
  ``min_overlap_mm2`` (a Boolean common of the two faces laid on one plane, with the fuzzy value
  ``overlap_fuzzy_mm`` so that exactly touching faces do not come out with nothing in common;
  touching along an edge is no mate). Pairs in contact also get ``parallel``/``perpendicular``
  rows for their largest principal faces.
- level "part": the ten relations of ``cadio.truth.relations.relate`` (view axis +Y for CAD).
- level "joint": the joint a CAD user would set, derived from the pair's coincident contacts and
  fits (``cadio.truth.joints``): ``relation`` is the suggested joint, ``kinematic`` the pure
  degree-of-freedom one, with Onshape / FreeCAD / Fusion 360 names.

Pruning (``cadio.truth.contact``) cannot change under a rigid motion of the whole assembly.
Coincident mates need contact: boxes enlarged by twice ``contact_mm`` skip only pairs that
cannot touch, and the mate test itself is exact; pairs "in contact" are within ``contact_mm``
(exact B-rep distance). Concentric mates do not need contact (a bolt in a clearance hole, the
two rings of a ball bearing): they are found by matching the axis lines of all parts, a test on
lines that is invariant by construction.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cadio.cad.step import StepSolid, read_step
from cadio.records import DIRECTIONAL, Features, Relation
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.contact import (
    SLACK,
    AxisFace,
    AxisLine,
    PartGeometry,
    box_pairs,
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
FIT, NESTED, ALIGNED = "fit", "nested", "aligned"


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
        tol: the tolerances (mate angle, contact, coaxial, parallel, freeform fit, fit
            clearance, smallest overlap area).
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
    clock.lap("prune")
    rows = _concentric_rows(parts, tol)
    rows += [r for i, j in boxed for r in _coincident_rows(parts[i], parts[j], tol)]
    clock.lap("face_mates")
    contact = contact_pairs(parts, boxed, *_contact_hints(rows, tol.contact_mm), tol.contact_mm)
    clock.lap("prune")
    relations = {(i, j): relate(parts[i].features, parts[j].features, view_axis, tol)
                 for i in range(len(parts)) for j in range(i + 1, len(parts))}
    rows += [r for (i, j), rr in relations.items() for r in _part_rows(parts[i], parts[j], rr)]
    rows += [r for i, j in contact
             for r in _principal_face_rows(parts[i], parts[j], relations[(i, j)])]
    clock.lap("relations")
    rows += _joint_rows(parts, rows, tol)
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
    (face ids, -1 when none), axis, origin (3 floats, assembly frame, or None), distance_mm,
    angle_deg, overlap_area_mm2, radial_gap_mm (NaN when not applicable), fit ("fit", "nested",
    "aligned" for concentric), kinematic, dof (-1 when none), onshape, freecad, fusion360 (joint
    names), evidence (text). ``table.attrs`` (tolerances, view axis) go in the metadata.
    """
    with atomic_path(Path(path)) as tmp:
        table.to_parquet(tmp, index=False)


def read_mates(path: Path | str) -> pd.DataFrame:
    """Read a mates table written by ``write_mates``."""
    return pd.read_parquet(Path(path))


def _contact_hints(rows: list[Row], tol: float) -> tuple[
        set[tuple[int, int]], dict[tuple[int, int], list[tuple[int, int]]]]:
    """The face mates as hints for ``contact_pairs``: pairs with a coincident mate (in contact),
    and per pair the face ids of concentric fits with a radial gap within ``tol`` mm."""
    mated = {(r["index_a"], r["index_b"]) for r in rows if r["relation"] == "coincident"}
    hints: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for r in rows:
        if r["relation"] == "concentric" and r["radial_gap_mm"] <= tol:
            hints.setdefault((r["index_a"], r["index_b"]), []).append((r["face_a"], r["face_b"]))
    return mated, hints


# ---------------------------------------------------------------- concentric


def _concentric_rows(parts: list[PartGeometry], tol: Tolerances) -> list[Row]:
    """One row per pair of coaxial axis lines of two parts that overlap along the axis."""
    owner = [(p.index, k) for p in parts for k in range(len(p.lines))]
    if len(owner) < 2:
        return []
    lines = [parts[i].lines[k] for i, k in owner]
    d = np.array([ln.direction for ln in lines])
    mid = np.array([ln.mid for ln in lines])
    ends = np.array([ln.ends for ln in lines])  # (n, 2, 3)
    part_of = np.array([i for i, _ in owner])
    rows = []
    for a in range(len(lines) - 1):
        b = np.arange(a + 1, len(lines))
        cross = np.linalg.norm(np.cross(d[a], d[b]), axis=1)
        angle = np.degrees(np.arctan2(cross, np.abs(d[b] @ d[a])))
        rel = mid[b] - mid[a]
        gap_b = np.linalg.norm(rel - np.outer(rel @ d[a], d[a]), axis=1)
        gap_a = np.linalg.norm(rel - (np.einsum("ij,ij->i", rel, d[b]))[:, None] * d[b], axis=1)
        ta, tb = ends[a] @ d[a], ends[b] @ d[a]  # (2,), (m, 2)
        overlap = np.minimum(ta.max(), tb.max(axis=1)) - np.maximum(ta.min(), tb.min(axis=1))
        keep = ((part_of[b] != part_of[a]) & (angle <= tol.coaxial_deg + SLACK)
                & (np.maximum(gap_a, gap_b) <= tol.coaxial_mm + SLACK)
                & (overlap >= -tol.contact_mm - SLACK))
        for k in np.nonzero(keep)[0]:
            pa, pb = parts[part_of[a]], parts[part_of[b[k]]]
            row = _concentric_row(pa, lines[a], pb, lines[b[k]], float(angle[k]),
                                  float(max(gap_a[k], gap_b[k])), tol)
            if row is not None:
                rows.append(row)
    return rows


def _concentric_row(pa: PartGeometry, la: AxisLine, pb: PartGeometry, lb: AxisLine,
                    angle: float, gap: float, tol: Tolerances) -> Row | None:
    """The mate of two coaxial lines, with the face pair that engages best as evidence."""
    if pa.index > pb.index:
        pa, la, pb, lb = pb, lb, pa, la
    found = []
    for fa in la.faces:
        for fb in lb.faces:
            ta, tb = fa.ends @ la.direction, fb.ends @ la.direction
            lo, hi = max(ta.min(), tb.min()), min(ta.max(), tb.max())
            if hi - lo >= -tol.contact_mm - SLACK:
                fit, radial = _fit(fa, fb, hi - lo, tol)
                found.append(((FIT, NESTED, ALIGNED).index(fit), hi - lo, radial, fa, fb, fit,
                              0.5 * (lo + hi)))
    if not found:
        return None
    # best fit class, then longest overlap, then smallest gap; near-ties (1e-6 mm, rounding
    # under a rigid motion) go to the smallest face ids
    found = [f for f in found if f[0] == min(g[0] for g in found)]
    found = [f for f in found if f[1] >= max(g[1] for g in found) - 1e-6]
    found = [f for f in found if f[2] <= min(g[2] for g in found) + 1e-6]
    _, overlap, radial, fa, fb, fit, t_mid = min(found, key=lambda f: (f[3].face_id, f[4].face_id))
    origin = la.mid + (t_mid - float(np.dot(la.mid, la.direction))) * la.direction
    evidence = (f"{fit}: face {fa.face_id} ({_kind(fa)} r={fa.radius:.3f}) and face "
                f"{fb.face_id} ({_kind(fb)} r={fb.radius:.3f}) overlap {overlap:.3f} mm along "
                f"the axis; coaxial faces a {[f.face_id for f in la.faces]}, "
                f"b {[f.face_id for f in lb.faces]}")
    return _row(pa, pb, "face", Relation.CONCENTRIC.value, face_a=fa.face_id, face_b=fb.face_id,
                axis=la.direction, origin=origin, distance_mm=gap, angle_deg=angle,
                radial_gap_mm=radial, fit=fit, evidence=evidence)


def _kind(f: AxisFace) -> str:
    return "shaft" if f.convex else "hole"


def _fit(fa: AxisFace, fb: AxisFace, overlap: float, tol: Tolerances) -> tuple[str, float]:
    """("fit" | "nested" | "aligned", radial gap mm) of two coaxial faces."""
    if fa.convex == fb.convex:
        return ALIGNED, abs(fa.radius - fb.radius)
    shaft, bore = (fa, fb) if fa.convex else (fb, fa)
    radial = bore.radius - shaft.radius
    if overlap <= tol.contact_mm or radial < -tol.coaxial_mm:
        return ALIGNED, abs(radial)  # abutting, or a boss beside a smaller hole
    return (FIT if radial <= tol.fit_clearance_mm + SLACK else NESTED), max(radial, 0.0)


# ---------------------------------------------------------------- coincident


def _coincident_rows(a: PartGeometry, b: PartGeometry, tol: Tolerances) -> list[Row]:
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
    rows = []
    for k, m in zip(*np.nonzero(opposed & (offset <= tol.contact_mm + SLACK) & near),
                    strict=True):
        area, centre = face_overlap(a.faces[a.plane_ids[k]], b.faces[b.plane_ids[m]],
                                    a.normals[k], a.centres[k], b.normals[m], b.centres[m],
                                    tol.overlap_fuzzy_mm)
        if area <= tol.min_overlap_mm2:
            continue
        angle = math.degrees(math.acos(min(1.0, -float(cos[k, m]))))
        rows.append(_row(
            a, b, "face", Relation.COINCIDENT.value, face_a=a.plane_ids[k],
            face_b=b.plane_ids[m], axis=a.normals[k], origin=centre,
            distance_mm=float(offset[k, m]), angle_deg=angle, overlap_area_mm2=area,
            evidence=f"planar faces {a.plane_ids[k]} / {b.plane_ids[m]} face to face, "
                     f"{offset[k, m]:.4f} mm apart, overlap {area:.3f} mm^2"))
    return rows


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


def _joint_rows(parts: list[PartGeometry], rows: list[Row], tol: Tolerances) -> list[Row]:
    """One joint row per pair with at least one coincident contact or concentric fit."""
    by_pair: dict[tuple[int, int], list[Constraint]] = {}
    for r in rows:
        if r["level"] != "face":
            continue
        if r["relation"] == Relation.COINCIDENT.value:
            kind = PLANE_CONTACT
        elif r["relation"] == Relation.CONCENTRIC.value and r["fit"] == FIT:
            kind = AXIS
        else:
            continue
        c = Constraint(kind, np.array(r["axis"]), np.array(r["origin"]))
        by_pair.setdefault((r["index_a"], r["index_b"]), []).append(c)
    out = []
    for (i, j), constraints in sorted(by_pair.items()):
        a, b = parts[i], parts[j]
        joint = derive_joint(constraints, (a.name, b.name), tol)
        assert joint is not None
        n_fit = sum(c.kind == AXIS for c in constraints)
        out.append(_row(
            a, b, "joint", joint.suggested, axis=joint.axis, origin=joint.origin,
            kinematic=joint.kinematic, dof=joint.dof, **joint.cad_names(),
            evidence=f"{joint.reason}; from {len(constraints) - n_fit} coincident contacts "
                     f"and {n_fit} fits"))
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


def mates_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Extract and write one assembly's mates (the job of an isolated worker in the flow).

    Args:
        payload: ``path`` (STEP), ``assembly`` (name), ``workspace``, ``part_ids`` (solid
            index -> catalog part id).

    Returns:
        Counts for the report: parts, pairs, pairs in contact, face mates, true part-level
        relations, joints, joints by suggested type, seconds per phase, the parquet path.
    """
    from cadio.workspace import Workspace

    result = read_assembly_mates(Path(payload["path"]),
                                 part_ids={int(k): v for k, v in payload["part_ids"].items()})
    out = Workspace(Path(payload["workspace"])).mates(str(payload["assembly"]))
    write_mates(out, result.table)
    joints = result.level("joint")
    return {
        "path": str(out), "n_parts": result.n_parts, "n_pairs": result.n_pairs,
        "n_box_pairs": result.n_box_pairs, "n_contact_pairs": result.n_contact_pairs,
        "face_mates": len(result.level("face")), "relations": len(result.level("part")),
        "joints": len(joints),
        "joint_types": {str(k): int(v) for k, v in joints["relation"].value_counts().items()},
        "phase_seconds": result.seconds,
    }
