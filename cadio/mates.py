"""Ground-truth mates of a CAD assembly: face-level mates, part-level relations and joints.

For every pair of parts (solids already in the assembly frame, mm), one table with ONE ROW PER
MATE, RELATION OR JOINT (``COLUMNS``, schema in ``write_mates``), for index_a < index_b, read
"a <relation> b":

- level "face": ``concentric`` between coaxial cylindrical/conical faces (axes within
  ``coaxial_deg``, lines within ``coaxial_mm``, overlapping along the axis or abutting within
  ``contact_mm``, any radii; ``fit`` says "fit" for a shaft in a bore with at most
  ``MateConfig.fit_clearance_mm`` of radial clearance, "nested" for a larger gap, "aligned" for
  two holes or two shafts), and ``coincident`` between planar faces with opposite outward normals
  (within ``mate_angle_deg``), planes within ``contact_mm`` and an overlap of positive area (a
  Boolean common of the two faces laid on one plane: touching along an edge is no mate). Pairs in
  contact also get ``parallel``/``perpendicular`` rows for their largest principal faces.
- level "part": the ten relations of ``cadio.relations.relate`` (view axis +Y for CAD).
- level "joint": the joint a CAD user would set, derived from the pair's coincident contacts and
  fits (``cadio.joints``): ``relation`` is the suggested joint, ``kinematic`` the pure
  degree-of-freedom one, with Onshape / FreeCAD / Fusion 360 names.

Pruning cannot change under a rigid motion of the whole assembly. Coincident mates need contact:
axis-aligned boxes enlarged by twice ``contact_mm`` skip only pairs that cannot touch (a box
bounds its solid in any frame), and the mate test itself is exact. The pairs "in contact" are
those whose exact B-rep distance is at most ``contact_mm`` (``cadio.joints.in_contact``). Concentric
mates do not need contact (a bolt in a clearance hole, the two rings of a ball bearing): they are
found by matching the axis lines of all parts, a test on lines that is invariant by construction.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from OCP.Bnd import Bnd_Box
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve
from OCP.BRepAlgoAPI import BRepAlgoAPI_Common
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepGProp import BRepGProp, BRepGProp_Face
from OCP.BRepTools import BRepTools
from OCP.gp import gp_Ax1, gp_Dir, gp_Pnt, gp_Trsf, gp_Vec
from OCP.GProp import GProp_GProps
from OCP.TopAbs import TopAbs_EDGE
from OCP.TopExp import TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape

from cadio.faces import CONE, indexed_faces
from cadio.features import extract_features
from cadio.joints import (
    AXIS,
    Constraint,
    ContactProxy,
    contact_proxy,
    derive_joint,
    faces_within,
    in_contact,
)
from cadio.joints import PLANE as PLANE_CONTACT
from cadio.records import DIRECTIONAL, AxisGroup, Features, FloatArray, Relation
from cadio.relations import CAD_VIEW_AXIS, RelationResult, relate
from cadio.step import StepSolid, read_step
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.workspace import atomic_path

log = logging.getLogger(__name__)

COLUMNS = (
    "assembly", "part_a", "part_b", "index_a", "index_b", "name_a", "name_b", "path_a", "path_b",
    "level", "relation", "face_a", "face_b", "axis", "origin", "distance_mm", "angle_deg",
    "overlap_area_mm2", "radial_gap_mm", "fit", "kinematic", "dof", "onshape", "freecad",
    "fusion360", "evidence",
)
LEVELS = ("face", "part", "joint")
Row = dict[str, Any]  # one table row, keys ``COLUMNS``
FIT, NESTED, ALIGNED = "fit", "nested", "aligned"
_SAMPLES_PER_EDGE = 9
_SLACK = 1e-9  # values computed exactly at a tolerance stay inside despite rounding


@dataclass(frozen=True)
class MateConfig:
    """Knobs of mate extraction beyond the shared tolerances (mm, mm^2)."""

    # A shaft inside a coaxial bore is a "fit" (a kinematic constraint, used for joints) when the
    # radial clearance is at most this; ISO 273 coarse clearance holes up to M24 are within 2 mm.
    fit_clearance_mm: float = 2.0
    # Coincident faces must overlap by more than this: a Boolean of faces sharing only an edge
    # can leave slivers of rounding size.
    min_overlap_mm2: float = 1e-6


@dataclass(frozen=True)
class MatesResult:
    """Mates of one assembly.

    table: one row per mate, relation or joint, columns ``COLUMNS``; ``table.attrs`` holds the
    tolerances, config and view axis. n_pairs: all unordered pairs of parts; n_box_pairs: pairs
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


@dataclass(frozen=True)
class _AxisFace:
    """A cylindrical or conical face: radius mm (cone: mean over its boundary), convex (a shaft
    or boss, not a hole), ends (2, 3) mm: its axis points at the lowest and highest axial end."""

    face_id: int
    radius: float
    convex: bool
    ends: FloatArray


@dataclass(frozen=True)
class _Line:
    """Coaxial faces of one part: unit direction, mid point and ends (2, 3) of their extent, mm."""

    direction: FloatArray
    mid: FloatArray
    ends: FloatArray
    faces: tuple[_AxisFace, ...]


@dataclass(frozen=True)
class _Part:
    """A part and what the mates need: planar faces (ids, outward normals (k, 3), area centroids
    (k, 3) mm, reach (k,) mm = largest distance from the centroid to the boundary) and axis lines.
    """

    index: int
    part_id: str
    name: str
    path: str
    shape: TopoDS_Shape
    features: Features
    faces: list[TopoDS_Face]
    plane_ids: list[int]
    normals: FloatArray
    centres: FloatArray
    reach: FloatArray
    lines: tuple[_Line, ...]


def extract_mates(
    solids: Sequence[StepSolid],
    tol: Tolerances = DEFAULT_TOLERANCES,
    view_axis: Sequence[float] = CAD_VIEW_AXIS,
    *,
    assembly: str = "",
    part_ids: Mapping[int, str] | None = None,
    config: MateConfig = MateConfig(),
) -> MatesResult:
    """Face-level mates, part-level relations and joints of every pair of parts.

    Args:
        solids: the assembly's solids, in the assembly frame (mm), as ``read_step`` returns them.
        tol: the tolerances (mate angle, contact, coaxial, parallel, freeform fit).
        view_axis: (3,) the observer's forward direction for left/right/front/behind (+Y for CAD).
        assembly: the assembly name written in every row.
        part_ids: solid index -> part id (default: the index as text).
        config: knobs beyond the tolerances (fit clearance, smallest overlap area).

    Returns:
        A ``MatesResult``: the table (no file is touched), pair counts and seconds per phase.

    Raises:
        GeometryError: a solid has no faces or no volume.
    """
    clock = _Clock()
    ids = part_ids or {}
    parts = [_describe_part(s, k, ids.get(s.info.index, str(s.info.index)), tol)
             for k, s in enumerate(solids)]
    clock.lap("features")
    boxed = _box_pairs(parts, 2.0 * tol.contact_mm)
    clock.lap("prune")
    rows = _concentric_rows(parts, tol, config)
    rows += [r for i, j in boxed for r in _coincident_rows(parts[i], parts[j], tol, config)]
    clock.lap("face_mates")
    contact = _contact_pairs(parts, boxed, rows, tol.contact_mm)  # uses the mates as hints
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
    table.attrs = {"tolerances": tol.as_dict(), "mate_config": asdict(config),
                   "view_axis": [float(v) for v in view_axis]}
    n = len(parts)
    return MatesResult(table, n, n * (n - 1) // 2, len(boxed), len(contact), clock.seconds)


def read_assembly_mates(
    path: Path | str,
    tol: Tolerances = DEFAULT_TOLERANCES,
    view_axis: Sequence[float] = CAD_VIEW_AXIS,
    *,
    part_ids: Mapping[int, str] | None = None,
    config: MateConfig = MateConfig(),
) -> MatesResult:
    """Read a STEP assembly and extract its mates; the assembly is named after the file stem.

    Raises:
        StepReadError: the file cannot be read.
    """
    start = time.perf_counter()
    solids = read_step(Path(path))
    read_s = time.perf_counter() - start
    result = extract_mates(solids, tol, view_axis, assembly=Path(path).stem,
                           part_ids=part_ids, config=config)
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
    names), evidence (text). ``table.attrs`` (tolerances, config, view axis) go in the metadata.
    """
    with atomic_path(Path(path)) as tmp:
        table.to_parquet(tmp, index=False)


def read_mates(path: Path | str) -> pd.DataFrame:
    """Read a mates table written by ``write_mates``."""
    return pd.read_parquet(Path(path))


# ---------------------------------------------------------------- per-part geometry


def _describe_part(solid: StepSolid, index: int, part_id: str, tol: Tolerances) -> _Part:
    """Features, planar faces and axis lines of one solid (assembly frame)."""
    shape = solid.shape
    faces = indexed_faces(shape)
    features = extract_features(shape, tol)
    ids, normals, centres, reach = [], [], [], []
    for g in features.planes:
        for fid, offset, outward in zip(g.face_ids, g.offsets, g.outward, strict=True):
            pts = _boundary(faces[fid])
            centre = pts.mean(axis=0) if len(pts) else g.normal * offset
            centre = centre - (float(np.dot(g.normal, centre)) - offset) * g.normal
            ids.append(fid)
            normals.append(outward * g.normal)
            centres.append(centre)
            reach.append(float(np.max(np.linalg.norm(pts - centre, axis=1))) if len(pts) else 0.0)
    return _Part(
        index=index, part_id=part_id, name=solid.info.name, path=solid.info.path_in_assembly,
        shape=shape, features=features, faces=faces, plane_ids=ids,
        normals=np.array(normals).reshape(-1, 3), centres=np.array(centres).reshape(-1, 3),
        reach=np.array(reach, dtype=np.float64), lines=_axis_lines(features.axes, faces, tol),
    )


def _boundary(face: TopoDS_Face) -> FloatArray:
    """Points sampled along the face's edges (m, 3), mm (degenerate edges skipped)."""
    points = []
    explorer = TopExp_Explorer(face, TopAbs_EDGE)
    while explorer.More():
        edge = TopoDS.Edge_s(explorer.Current())
        explorer.Next()
        if BRep_Tool.Degenerated_s(edge):
            continue
        curve = BRepAdaptor_Curve(edge)
        for u in np.linspace(curve.FirstParameter(), curve.LastParameter(), _SAMPLES_PER_EDGE):
            p = curve.Value(float(u))
            points.append((p.X(), p.Y(), p.Z()))
    return np.array(points, dtype=np.float64).reshape(-1, 3)


def _axis_face(face_id: int, face: TopoDS_Face, kind: str, radius: float, d: FloatArray,
               point: FloatArray) -> _AxisFace:
    """One face on the axis line (d unit, point): its axial ends, radius and convexity."""
    pts = _boundary(face)
    rel = pts - point
    t = rel @ d
    if kind == CONE and len(pts):  # the cone's reference radius may be anywhere on its axis
        radius = float(np.linalg.norm(rel - np.outer(t, d), axis=1).mean())
    ends = point + np.outer([t.min(), t.max()] if len(t) else [0.0, 0.0], d)
    return _AxisFace(face_id, float(radius), _is_convex(face, point, d), ends)


def _is_convex(face: TopoDS_Face, point: FloatArray, d: FloatArray) -> bool:
    """True when the face's outward normal points away from its axis (a shaft, not a hole)."""
    gprop = BRepGProp_Face(face)
    umin, umax, vmin, vmax = BRepTools.UVBounds_s(face)
    best = 0.0
    for fu, fv in ((0.5, 0.5), (0.25, 0.25), (0.75, 0.75), (0.25, 0.75), (0.75, 0.25)):
        p, n = gp_Pnt(), gp_Vec()
        gprop.Normal(umin + fu * (umax - umin), vmin + fv * (vmax - vmin), p, n)
        rel = np.array([p.X(), p.Y(), p.Z()]) - point
        radial = rel - np.dot(rel, d) * d
        value = float(np.dot(radial, [n.X(), n.Y(), n.Z()]))
        if abs(value) > abs(best):
            best = value
    return best > 0.0


def _axis_lines(groups: Sequence[AxisGroup], faces: list[TopoDS_Face],
                tol: Tolerances) -> tuple[_Line, ...]:
    """Merge the part's cylinder and cone axis groups that share a line (greedy, in order)."""
    clusters: list[list[AxisGroup]] = []
    for g in groups:
        for c in clusters:
            if _coaxial(c[0].direction, c[0].point, g.direction, g.point, tol):
                c.append(g)
                break
        else:
            clusters.append([g])
    lines = []
    for members in clusters:
        d, base = members[0].direction, members[0].point
        axis_faces = tuple(
            _axis_face(fid, faces[fid], g.kind, r, d, base)
            for g in members for fid, r in zip(g.face_ids, g.radii, strict=True))
        t = np.concatenate([f.ends @ d for f in axis_faces])
        ends = base + np.outer([t.min(), t.max()], d)
        lines.append(_Line(d, ends.mean(axis=0), ends, axis_faces))
    return tuple(lines)


def _coaxial(da: FloatArray, pa: FloatArray, db: FloatArray, pb: FloatArray,
             tol: Tolerances) -> bool:
    angle = math.degrees(math.atan2(np.linalg.norm(np.cross(da, db)), abs(np.dot(da, db))))
    gap = _line_gap(pa, da, pb, db)
    return angle <= tol.coaxial_deg + _SLACK and gap <= tol.coaxial_mm + _SLACK


def _line_gap(pa: FloatArray, da: FloatArray, pb: FloatArray, db: FloatArray) -> float:
    """Largest distance of either point from the other's axis line (unit directions), mm."""
    def off(p: FloatArray, q: FloatArray, d: FloatArray) -> float:
        r = p - q
        return float(np.linalg.norm(r - np.dot(r, d) * d))

    return max(off(pa, pb, db), off(pb, pa, da))


# ---------------------------------------------------------------- pruning


def _box_pairs(parts: list[_Part], margin: float) -> list[tuple[int, int]]:
    """Pairs (i < j) whose bounding boxes, enlarged by ``margin`` mm, overlap."""
    if len(parts) < 2:
        return []
    lo, hi = np.empty((len(parts), 3)), np.empty((len(parts), 3))
    for k, part in enumerate(parts):
        box = Bnd_Box()
        BRepBndLib.Add_s(part.shape, box, False)  # from the geometry, enlarged by its tolerance
        lo[k], hi[k] = box.Get()[:3], box.Get()[3:]
    hit = np.all((lo[:, None, :] <= hi[None, :, :] + margin)
                 & (lo[None, :, :] <= hi[:, None, :] + margin), axis=2)
    i, j = np.nonzero(np.triu(hit, k=1))
    return list(zip(i.tolist(), j.tolist(), strict=True))


def _contact_pairs(parts: list[_Part], boxed: list[tuple[int, int]], rows: list[Row],
                   tol: float) -> list[tuple[int, int]]:
    """Pairs within ``tol`` mm (exact). A coincident mate proves contact; a concentric fit with
    a radial gap within ``tol`` is measured on its two faces first; the rest by ``in_contact``."""
    mated = {(r["index_a"], r["index_b"]) for r in rows if r["relation"] == "coincident"}
    hints: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for r in rows:
        if r["relation"] == "concentric" and r["radial_gap_mm"] <= tol:
            hints.setdefault((r["index_a"], r["index_b"]), []).append((r["face_a"], r["face_b"]))
    proxies: dict[int, ContactProxy] = {}

    def touching(i: int, j: int) -> bool:
        if (i, j) in mated or faces_within(parts[i].faces, parts[j].faces,
                                           hints.get((i, j), []), tol):
            return True
        for k in (i, j):
            if k not in proxies:
                proxies[k] = contact_proxy(parts[k].shape, parts[k].plane_ids)
        return in_contact(proxies[i], proxies[j], tol)

    return [(i, j) for i, j in boxed if touching(i, j)]


# ---------------------------------------------------------------- concentric


def _concentric_rows(parts: list[_Part], tol: Tolerances, cfg: MateConfig) -> list[Row]:
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
        keep = ((part_of[b] != part_of[a]) & (angle <= tol.coaxial_deg + _SLACK)
                & (np.maximum(gap_a, gap_b) <= tol.coaxial_mm + _SLACK)
                & (overlap >= -tol.contact_mm - _SLACK))
        for k in np.nonzero(keep)[0]:
            pa, pb = parts[part_of[a]], parts[part_of[b[k]]]
            row = _concentric_row(pa, lines[a], pb, lines[b[k]], float(angle[k]),
                                  float(max(gap_a[k], gap_b[k])), tol, cfg)
            if row is not None:
                rows.append(row)
    return rows


def _concentric_row(pa: _Part, la: _Line, pb: _Part, lb: _Line, angle: float, gap: float,
                    tol: Tolerances, cfg: MateConfig) -> Row | None:
    """The mate of two coaxial lines, with the face pair that engages best as evidence."""
    if pa.index > pb.index:
        pa, la, pb, lb = pb, lb, pa, la
    found = []
    for fa in la.faces:
        for fb in lb.faces:
            ta, tb = fa.ends @ la.direction, fb.ends @ la.direction
            lo, hi = max(ta.min(), tb.min()), min(ta.max(), tb.max())
            if hi - lo >= -tol.contact_mm - _SLACK:
                fit, radial = _fit(fa, fb, hi - lo, tol, cfg)
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


def _kind(f: _AxisFace) -> str:
    return "shaft" if f.convex else "hole"


def _fit(fa: _AxisFace, fb: _AxisFace, overlap: float, tol: Tolerances,
         cfg: MateConfig) -> tuple[str, float]:
    """("fit" | "nested" | "aligned", radial gap mm) of two coaxial faces."""
    if fa.convex == fb.convex:
        return ALIGNED, abs(fa.radius - fb.radius)
    shaft, bore = (fa, fb) if fa.convex else (fb, fa)
    radial = bore.radius - shaft.radius
    if overlap <= tol.contact_mm or radial < -tol.coaxial_mm:
        return ALIGNED, abs(radial)  # abutting, or a boss beside a smaller hole
    return (FIT if radial <= cfg.fit_clearance_mm + _SLACK else NESTED), max(radial, 0.0)


# ---------------------------------------------------------------- coincident


def _coincident_rows(a: _Part, b: _Part, tol: Tolerances, cfg: MateConfig) -> list[Row]:
    """Planar faces of two parts in contact: opposite normals, planes close, positive overlap."""
    if not len(a.plane_ids) or not len(b.plane_ids):
        return []
    cos = a.normals @ b.normals.T  # (ka, kb)
    opposed = cos <= -math.cos(math.radians(tol.mate_angle_deg)) + _SLACK
    rel = b.centres[None, :, :] - a.centres[:, None, :]  # (ka, kb, 3)
    along = np.einsum("ijk,ik->ij", rel, a.normals)
    offset = np.maximum(np.abs(along), np.abs(np.einsum("ijk,jk->ij", rel, b.normals)))
    inplane = np.linalg.norm(rel - along[..., None] * a.normals[:, None, :], axis=2)
    near = inplane <= a.reach[:, None] + b.reach[None, :] + tol.contact_mm
    rows = []
    for k, m in zip(*np.nonzero(opposed & (offset <= tol.contact_mm + _SLACK) & near),
                    strict=True):
        area, centre = _overlap(a.faces[a.plane_ids[k]], b.faces[b.plane_ids[m]],
                                a.normals[k], a.centres[k], b.normals[m], b.centres[m])
        if area <= cfg.min_overlap_mm2:
            continue
        angle = math.degrees(math.acos(min(1.0, -float(cos[k, m]))))
        rows.append(_row(
            a, b, "face", Relation.COINCIDENT.value, face_a=a.plane_ids[k],
            face_b=b.plane_ids[m], axis=a.normals[k], origin=centre,
            distance_mm=float(offset[k, m]), angle_deg=angle, overlap_area_mm2=area,
            evidence=f"planar faces {a.plane_ids[k]} / {b.plane_ids[m]} face to face, "
                     f"{offset[k, m]:.4f} mm apart, overlap {area:.3f} mm^2"))
    return rows


def _overlap(fa: TopoDS_Face, fb: TopoDS_Face, na: FloatArray, ca: FloatArray,
             nb: FloatArray, cb: FloatArray) -> tuple[float, FloatArray]:
    """(area mm^2, centroid (3,) mm) of the overlap of two nearly coplanar, opposed faces.

    Face b is turned about its centroid until its normal is exactly -na and shifted onto a's
    plane (a motion of at most ``mate_angle_deg`` and ``contact_mm``), then intersected with a.
    """
    axis = np.cross(nb, -na)
    sin = float(np.linalg.norm(axis))
    turn = gp_Trsf()
    if sin > 1e-12:
        turn.SetRotation(gp_Ax1(gp_Pnt(*cb), gp_Dir(*(axis / sin))),
                         math.atan2(sin, float(np.dot(nb, -na))))
    shift = gp_Trsf()
    shift.SetTranslation(gp_Vec(*(-float(np.dot(cb - ca, na)) * na)))
    moved = fb.Moved(TopLoc_Location(shift.Multiplied(turn)))
    common = BRepAlgoAPI_Common(fa, moved)
    if not common.IsDone():
        log.warning("Boolean common of two planar faces failed: no overlap assumed")
        return 0.0, ca
    props = GProp_GProps()
    BRepGProp.SurfaceProperties_s(common.Shape(), props)
    c = props.CentreOfMass()
    return float(props.Mass()), np.array([c.X(), c.Y(), c.Z()])


# ---------------------------------------------------------------- part level


def _part_rows(a: _Part, b: _Part, rr: RelationResult) -> list[Row]:
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


def _principal_face_rows(a: _Part, b: _Part, rr: RelationResult) -> list[Row]:
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


def _joint_rows(parts: list[_Part], rows: list[Row], tol: Tolerances) -> list[Row]:
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


def _row(a: _Part, b: _Part, level: str, relation: str, **values: Any) -> Row:
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
