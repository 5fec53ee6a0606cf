"""Ground-truth mates of a CAD assembly: face-level mates, part-level relations and joints.

For every pair of parts (solids already in the assembly frame, mm), one table with ONE ROW PER
MATE, RELATION OR JOINT (``COLUMNS``, schema in ``write_mates``), for index_a < index_b, read
"a <relation> b":

- level "face": the face mates of ``cadio.truth.facemates``: ``concentric``, one row per pair
  of coaxial cylindrical/conical faces (axes within ``coaxial_deg``, lines within
  ``coaxial_mm``) whose faces lie within ``concentric_gap_mm`` of each other (exact
  face-to-face distance): ``fit`` says "fit" when the radii agree within ``fit_radius_mm``
  (cones: semi-angles within ``mate_angle_deg`` and radii within ``fit_radius_mm`` at a common
  axial station) and "clearance" otherwise (a gland beside a shaft across fillets, a bolt in a
  clearance hole; a cylinder against a cone). ``coincident`` between planar faces with opposite
  outward normals (within ``mate_angle_deg``), planes within ``contact_mm`` and an overlap of
  more than ``min_overlap_mm2`` (touching along an edge is no mate). Pairs in contact also get
  ``parallel``/``perpendicular`` rows for the largest faces of their dominant plane directions.
- level "part": the ten relations of ``cadio.truth.labels.label_placed`` (view axis +Y for
  CAD), the one truth of scenes and assemblies: a pair is ``concentric`` / ``coincident`` at
  part level exactly when it has a face mate of that kind.
- level "joint": the joint a CAD user would set, derived from the pair's coincident contacts and
  shafts in bores (``cadio.truth.joints``): ``relation`` is the suggested joint, ``kinematic``
  the pure degree-of-freedom one, with Onshape / FreeCAD / Fusion 360 names.

``table.attrs`` holds the tolerances, the view axis and ``near_boundary``: (part_a, part_b,
relation) of every concentric or coincident answer within the margins of a tolerance.

Pruning cannot change under a rigid motion of the whole assembly (``cadio.truth.proximity``):
boxes enlarged beyond the tolerances skip only pairs that cannot touch, and the tests after them
are exact; pairs "in contact" are within ``contact_mm`` (exact B-rep distance).
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

from cadio.cad.faces import CYLINDER
from cadio.cad.step import StepSolid, read_step
from cadio.records import DIRECTIONAL, Features, Relation
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.contact import SLACK, AxisFace, PartGeometry, describe_part
from cadio.truth.facemates import Coincident, Concentric
from cadio.truth.joints import AXIS, Constraint, derive_joint
from cadio.truth.joints import PLANE as PLANE_CONTACT
from cadio.truth.labels import PlacedLabels, label_placed
from cadio.truth.proximity import PartModel, box_pairs, contact_pairs
from cadio.truth.relations import (
    CAD_VIEW_AXIS,
    DEFAULT_MARGINS,
    BoundaryMargins,
    RelationResult,
)
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
    margins: BoundaryMargins = DEFAULT_MARGINS,
) -> MatesResult:
    """Face-level mates, part-level relations and joints of every pair of parts.

    Args:
        solids: the assembly's solids, in the assembly frame (mm), as ``read_step`` returns them.
        tol: the tolerances (mate angle, contact, coaxial, concentric gap, fit radius,
            parallel, dominant direction, freeform fit, smallest overlap area and its fuzzy
            value).
        view_axis: (3,) the observer's forward direction for left/right/front/behind (+Y for CAD).
        assembly: the assembly name written in every row.
        part_ids: solid index -> part id (default: the index as text).
        margins: what counts as near a tolerance (``table.attrs["near_boundary"]``).

    Returns:
        A ``MatesResult``: the table (no file is touched), pair counts and seconds per phase.

    Raises:
        GeometryError: a solid has no faces or no volume.
    """
    clock = _Clock()
    ids = part_ids or {}
    models = [PartModel(describe_part(s, k, ids.get(s.info.index, str(s.info.index)), tol))
              for k, s in enumerate(solids)]
    clock.lap("features")
    labels = label_placed(models, [np.eye(4)] * len(models), view_axis, tol, margins)
    parts = labels.parts
    mates = _face_mates(labels, tol)
    rows = [m.row for m in mates]
    clock.lap("face_mates")
    boxed = box_pairs(parts, 2.0 * tol.contact_mm)
    touching = {(m.row["index_a"], m.row["index_b"]) for m in mates if m.touching}
    contact = contact_pairs(parts, boxed, touching, tol.contact_mm, labels.proxies)
    clock.lap("prune")
    n = len(parts)
    relations = {(i, j): labels.relation(i, j) for i in range(n) for j in range(i + 1, n)}
    rows += [r for (i, j), rr in relations.items() for r in _part_rows(parts[i], parts[j], rr)]
    rows += [r for i, j in contact
             for r in _dominant_face_rows(parts[i], parts[j], relations[(i, j)], tol)]
    clock.lap("relations")
    rows += _joint_rows(parts, mates, tol)
    clock.lap("joints")
    table = _table(rows, assembly)
    table.attrs = {"tolerances": tol.as_dict(), "view_axis": [float(v) for v in view_axis],
                   "near_boundary": _near_answers(parts, labels.face_mates.contacts)}
    return MatesResult(table, n, n * (n - 1) // 2, len(boxed), len(contact), clock.seconds)


def _near_answers(parts: Sequence[PartGeometry], contacts: Mapping[tuple[int, int], Any]
                  ) -> list[list[str]]:
    """(part_a, part_b, relation) of the concentric and coincident answers near a boundary."""
    out = []
    for (i, j), c in sorted(contacts.items()):
        for relation in ("concentric", "coincident"):
            if getattr(c, f"{relation}_near"):
                out.append([parts[i].part_id, parts[j].part_id, relation])
    return out


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


# ---------------------------------------------------------------- face mates as rows


def _concentric_mate(mate: Concentric, tol: Tolerances) -> _FaceMate:
    """The row of two coaxial faces ``distance`` mm apart, read at their common axial station
    (the middle of their overlap along a's axis, or of the gap between their nearest ends)."""
    c, distance = mate.coaxial, mate.distance_mm
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


def _coincident_mate(parts: Sequence[PartGeometry], c: Coincident) -> _FaceMate:
    """The row of two planar faces face to face."""
    row = _row(
        parts[c.a], parts[c.b], "face", Relation.COINCIDENT.value, face_a=c.face_a,
        face_b=c.face_b, axis=c.normal, origin=c.centre, distance_mm=c.offset_mm,
        angle_deg=c.angle_deg, overlap_area_mm2=c.area_mm2,
        evidence=f"planar faces {c.face_a} / {c.face_b} face to face, "
                 f"{c.offset_mm:.4f} mm apart, overlap {c.area_mm2:.3f} mm^2")
    return _FaceMate(row, (Constraint(PLANE_CONTACT, c.normal, c.centre),), True)


# ---------------------------------------------------------------- part level


def _part_rows(a: PartGeometry, b: PartGeometry, rr: RelationResult) -> list[Row]:
    """One row per relation of the truth that holds for (a, b); face ids stay -1 (a pair may
    have many face mates: the face rows name them)."""
    rows = []
    for rel in rr.holding():
        dist, angle, evidence = _part_evidence(rel, rr)
        rows.append(_row(a, b, "part", rel.value, distance_mm=dist, angle_deg=angle,
                         evidence=evidence))
    return rows


def _part_evidence(rel: Relation, rr: RelationResult) -> tuple[float, float, str]:
    """(distance mm, angle deg, text) that decided one part-level relation."""
    nan = float("nan")
    if rel in (Relation.PARALLEL, Relation.PERPENDICULAR):
        angle = nan if rr.plane_angle_deg is None else rr.plane_angle_deg
        return nan, angle, f"dominant plane directions {angle:.3f} deg apart"
    if rel == Relation.COINCIDENT:
        gap = rr.contact.coincident_gap_mm
        return gap, nan, f"coincident face mates, planes {gap:.4f} mm apart at the closest"
    if rel == Relation.CONCENTRIC:
        gap = rr.contact.concentric_gap_mm
        return gap, nan, f"concentric face mates, faces {gap:.4f} mm apart at the closest"
    angle = rr.direction_deg[DIRECTIONAL.index(rel)]
    return rr.centre_distance_mm, angle, f"b to a {angle:.2f} deg off the {rel.value} axis"


def _dominant_face_rows(a: PartGeometry, b: PartGeometry, rr: RelationResult,
                        tol: Tolerances) -> list[Row]:
    """Face-level parallel / perpendicular rows for the largest faces of the dominant plane
    directions of parts in contact (the part-level truth)."""
    faces = {"face_a": _largest_dominant_face(a.features, tol),
             "face_b": _largest_dominant_face(b.features, tol)}
    return [_row(a, b, "face", rel.value, angle_deg=rr.plane_angle_deg, **faces,
                 evidence="largest faces of the dominant plane directions")
            for rel in (Relation.PARALLEL, Relation.PERPENDICULAR) if rr[rel]]


def _largest_dominant_face(f: Features, tol: Tolerances) -> int:
    """Id of the largest face of the dominant plane direction (near-ties: smallest id)."""
    dominant = f.dominant_plane
    if dominant is None:
        return -1
    cos = math.cos(math.radians(tol.dominant_group_deg))
    faces = [(area, i) for g in f.planes if abs(float(np.dot(g.normal, dominant))) >= cos - 1e-9
             for i, area in zip(g.face_ids, g.face_areas, strict=True)]
    if not faces:
        return -1
    top = max(area for area, _ in faces)
    return min(i for area, i in faces if area >= top * (1.0 - 1e-6))


# ---------------------------------------------------------------- joints and the table


def placed_joints(labels: PlacedLabels, tol: Tolerances = DEFAULT_TOLERANCES
                  ) -> dict[tuple[int, int], str]:
    """The kinematic joint of every pair (i < j, indices of ``labels.parts``) whose face mates
    constrain it, read as ``extract_mates`` reads it (the training corpus's joint labels)."""
    out = {}
    for (i, j), constraints in _constraints_by_pair(_face_mates(labels, tol)).items():
        joint = derive_joint(constraints, tol=tol)
        assert joint is not None
        out[(min(i, j), max(i, j))] = joint.kinematic
    return out


def _face_mates(labels: PlacedLabels, tol: Tolerances) -> list[_FaceMate]:
    """The concentric, then the coincident face mates of placed parts, as rows."""
    coincident, concentric = labels.face_mates.mates()
    mates = [_concentric_mate(c, tol) for c in concentric]
    return mates + [_coincident_mate(labels.parts, c) for c in coincident]


def _constraints_by_pair(mates: Sequence[_FaceMate]) -> dict[tuple[int, int], list[Constraint]]:
    """(index_a, index_b) -> the kinematic constraints of the pair's face mates (pairs whose
    mates constrain nothing are absent)."""
    by_pair: dict[tuple[int, int], list[Constraint]] = {}
    for m in mates:
        if m.constraints:
            by_pair.setdefault((m.row["index_a"], m.row["index_b"]), []).extend(m.constraints)
    return by_pair


def _joint_rows(parts: Sequence[PartGeometry], mates: list[_FaceMate],
                tol: Tolerances) -> list[Row]:
    """One joint row per pair with at least one coincident contact or shaft in a bore."""
    out = []
    for (i, j), constraints in sorted(_constraints_by_pair(mates).items()):
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
