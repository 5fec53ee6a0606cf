"""A CadQuery assembly script with the predicted mates as constraints.

The script is standalone (CadQuery and numpy only). It reads the parts from the STEP file,
finds each one by its volume and centroid, takes it back to its own frame (the inverse of its
placement in the file) and adds it to a ``cq.Assembly`` at its placement. Each predicted mate
with a CAD face mate behind it becomes constraints on that face geometry:

- coincident planar faces: ``Axis`` (the two face normals opposite) and ``PointInPlane`` (a
  point of b's face in a's plane): 3 equations;
- concentric faces: ``Axis`` (the two axes parallel) and ``PointOnLine`` (a point of b's axis on
  a's): 4 equations.

A predicted mate without a CAD face mate has no geometry to constrain and a CAD face mate whose
relation was not predicted is not a constraint: both stay in the sidecar and the notes with
their status, and the script lists them in its data. The part of each connected group of
constrained parts with the largest volume is ``Fixed`` (the anchor); a part without any
constraint keeps its placement. ``python script.py --json out.json`` solves and writes the
solved placements, their differences from the file's, and every constraint's residual;
``--perturb MM`` starts each constrained part MM away along a direction its constraints fix,
so the solve has work to do.

Names, paths and every other string read from input (a supplier's STEP file may name a part
anything, quotes and newlines included) go only into the script's data: one JSON document, all
printable ASCII, in a raw string literal that no JSON text can close. The rest of the script is
the same text for every assembly with the same tolerances.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from OCP.BRepGProp import BRepGProp
from OCP.GProp import GProp_GProps

from cadio.cad.step import StepSolid
from cadio.export.predictions import AssemblyMates, FaceGeometry, PairMates
from cadio.records import FloatArray
from cadio.truth.joints import AXIS, PLANE, Constraint, motion_equations
from cadio.workspace import atomic_write


def mass_properties(solids: Sequence[StepSolid]) -> dict[int, tuple[float, list[float]]]:
    """Volume (mm^3) and centroid (mm, file frame) of each solid by index: how the script
    finds the parts again in the STEP file, whatever order a reader returns them in."""
    out = {}
    for solid in solids:
        props = GProp_GProps()
        BRepGProp.VolumeProperties_s(solid.shape, props)
        c = props.CentreOfMass()
        out[solid.info.index] = (float(props.Mass()), [c.X(), c.Y(), c.Z()])
    return out


def _matrix(placement: Sequence[float]) -> FloatArray:
    return np.asarray(placement, dtype=np.float64).reshape(4, 4)


def _local_point(m: FloatArray, p: Sequence[float] | FloatArray) -> list[float]:
    inv = np.linalg.inv(m)
    return [float(v) for v in (inv @ np.array([*p, 1.0]))[:3]]


def _local_dir(m: FloatArray, d: Sequence[float] | FloatArray) -> list[float]:
    v = np.linalg.inv(m[:3, :3]) @ np.asarray(d, dtype=np.float64)
    return [float(x) for x in v / np.linalg.norm(v)]


def _across(axis: Sequence[float]) -> list[float]:
    """A unit direction perpendicular to ``axis``."""
    a = np.asarray(axis, dtype=np.float64)
    helper = np.eye(3)[int(np.argmin(np.abs(a)))]
    v = np.cross(a, helper)
    return [float(x) for x in v / np.linalg.norm(v)]


def _constraints(face: FaceGeometry, key_a: str, key_b: str, ma: FloatArray, mb: FloatArray
                 ) -> list[dict[str, Any]]:
    """The constraints of one face mate: the two markers' directions (``Axis``: opposite
    face normals, or parallel axes) and a point of b's on a's plane or axis."""
    n, o = face.axis, face.origin
    plane = face.relation == "coincident"
    shape, second, angle = ("plane", "PointInPlane", 180.0) if plane else (
        "line", "PointOnLine", 0.0)
    marker_a = {shape: [_local_point(ma, o), _local_dir(ma, n)]}
    marker_b = {shape: [_local_point(mb, o), _local_dir(mb, [-x for x in n] if plane else n)]}
    return [
        {"kind": "Axis", "a": key_a, "a_marker": marker_a, "b": key_b, "b_marker": marker_b,
         "param": angle, "mate": face.relation},
        {"kind": second, "a": key_b, "a_marker": {"point": _local_point(mb, o)},
         "b": key_a, "b_marker": marker_a, "param": None, "mate": face.relation},
    ]


def _as_constraint(face: FaceGeometry) -> Constraint:
    return Constraint(kind=PLANE if face.relation == "coincident" else AXIS,
                      direction=np.asarray(face.axis, dtype=np.float64),
                      point=np.asarray(face.origin, dtype=np.float64))


def _holds(key_a: str, key_b: str, faces: Sequence[FaceGeometry], ma: FloatArray,
           mb: FloatArray) -> list[dict[str, Any]]:
    """Constraints that hold b where the file has it in the motions its mates with a leave
    free (a revolute joint's angle, a slider's travel): what a CAD user sets as the joint's
    current value. One at a time from the null space of the mates' twist equations
    (``cadio.truth.joints``): a free rotation about w gets an ``Axis`` on a direction across
    w, a free translation along t a ``PointInPlane`` across t."""
    rows, centre, _scale = motion_equations([_as_constraint(f) for f in faces])
    out: list[dict[str, Any]] = []
    for _ in range(6):
        _, sv, vt = np.linalg.svd(rows)
        rank = int(np.sum(sv > 1e-6))
        if rank >= 6:
            break
        x = vt[rank]
        w, v = x[:3], x[3:]
        zero = np.zeros(3)
        if np.linalg.norm(w) > 0.1:
            axis = w / np.linalg.norm(w)
            across = np.asarray(_across(axis))
            other = np.cross(axis, across)
            marker_a = {"line": [_local_point(ma, centre), _local_dir(ma, across)]}
            marker_b = {"line": [_local_point(mb, centre), _local_dir(mb, across)]}
            out.append({"kind": "Axis", "a": key_a, "a_marker": marker_a, "b": key_b,
                        "b_marker": marker_b, "param": 0.0, "mate": "hold"})
            rows = np.vstack([rows, np.r_[axis, zero], np.r_[other, zero]])
        else:
            t = v / np.linalg.norm(v)
            out.append({"kind": "PointInPlane", "a": key_b,
                        "a_marker": {"point": _local_point(mb, centre)}, "b": key_a,
                        "b_marker": {"plane": [_local_point(ma, centre), _local_dir(ma, t)]},
                        "param": None, "mate": "hold"})
            rows = np.vstack([rows, np.r_[zero, t]])
    return out


def _tree(edges: list[tuple[int, int]], anchors: list[int]) -> dict[int, int]:
    """Each constrained part's parent on a shortest path of mates to its group's anchor."""
    parent: dict[int, int] = {}
    frontier = list(anchors)
    seen = set(anchors)
    while frontier:
        nxt = []
        for i in frontier:
            for a, b in edges:
                j = b if a == i else a if b == i else None
                if j is not None and j not in seen:
                    seen.add(j)
                    parent[j] = i
                    nxt.append(j)
        frontier = nxt
    return parent


def script_data(mates: AssemblyMates, step: Path,
                props: dict[int, tuple[float, list[float]]]) -> dict[str, Any]:
    """What the script embeds: parts, constraints (mates and holds), anchors, perturbation
    directions, and the mates that are no constraint with the reason."""
    key = {p.index: f"p{p.index}" for p in mates.parts}
    placements = {p.index: _matrix(p.placement) for p in mates.parts}
    constraints: list[dict[str, Any]] = []
    direction: dict[str, list[float]] = {}
    edges: list[tuple[int, int]] = []
    used_faces: dict[tuple[int, int], tuple[FaceGeometry, ...]] = {}
    left_out: list[str] = []
    for pair in mates.pairs:
        used = pair.constraints()
        for f in used:
            constraints += _constraints(f, key[pair.a.index], key[pair.b.index],
                                        placements[pair.a.index], placements[pair.b.index])
            move = list(f.axis) if f.relation == "coincident" else _across(f.axis)
            direction.setdefault(key[pair.b.index], move)
            direction.setdefault(key[pair.a.index], move)
        if used:
            edges.append((pair.a.index, pair.b.index))
            used_faces[(pair.a.index, pair.b.index)] = used
        left_out += _left_out(pair, used)
    anchors = _anchors(edges, {p.index: props[p.index][0] for p in mates.parts})
    for child, parent in sorted(_tree(edges, anchors).items()):
        faces = used_faces.get((parent, child)) or used_faces[(child, parent)]
        constraints += _holds(key[parent], key[child], faces, placements[parent],
                              placements[child])
    return {
        "assembly": mates.assembly, "step": str(step), "sha256": mates.source_sha256,
        "run_id": mates.run_id,
        "parts": [{"key": key[p.index], "index": p.index, "name": p.name,
                   "placement": list(p.placement), "volume": props[p.index][0],
                   "centroid": props[p.index][1]} for p in mates.parts],
        "anchors": [key[i] for i in anchors],
        "constraints": constraints,
        "perturb_direction": {k: v for k, v in direction.items()
                              if k not in {key[i] for i in anchors}},
        "unconstrained": left_out,
    }


def _left_out(pair: PairMates, used: Sequence[FaceGeometry]) -> list[str]:
    """Concentric and coincident answers of the pair that are no constraint, with why."""
    out = []
    for c in pair.relations:
        if c.relation not in ("concentric", "coincident"):
            continue
        faces = any(f.relation == c.relation for f in pair.faces)
        if c.predicted and any(f.relation == c.relation for f in used):
            continue
        if c.predicted is None:
            why = "not captured" if faces or c.cad else ""
        elif c.predicted:
            why = "predicted; the CAD has no such face mate"
        else:
            why = "the CAD's face mate was not predicted" if faces else ""
        if why:
            out.append(f"{pair.a.name} / {pair.b.name}: {c.relation} ({why})")
    return out


def _anchors(edges: list[tuple[int, int]], volume: dict[int, float]) -> list[int]:
    """The largest part of each connected group of constrained parts."""
    parent = {i: i for e in edges for i in e}

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in edges:
        parent[root(a)] = root(b)
    groups: dict[int, list[int]] = {}
    for i in parent:
        groups.setdefault(root(i), []).append(i)
    return sorted(max(g, key=lambda i: (volume[i], -i)) for g in groups.values())


def data_block(data: dict[str, Any]) -> str:
    """The script's data as the text between ``r\"\"\"`` and ``\"\"\"``: JSON with every
    character outside printable ASCII escaped, so no string in it holds a newline, a quote
    that is not escaped, or a trailing backslash (nothing in it can end the literal)."""
    text = json.dumps(data, indent=1, ensure_ascii=True, allow_nan=False)
    assert '"""' not in text and text.isascii() and "\r" not in text  # JSON escapes these
    return text


def write_script(path: Path, mates: AssemblyMates, step: Path,
                 props: dict[int, tuple[float, list[float]]], tolerance_mm: float,
                 tolerance_deg: float) -> Path:
    """Write the assembly's CadQuery script atomically; its path."""
    text = (_TEMPLATE
            .replace("@TOL_MM@", repr(float(tolerance_mm)))
            .replace("@TOL_DEG@", repr(float(tolerance_deg)))
            .replace("@DATA@", data_block(script_data(mates, step, props))))  # last: data
    with atomic_write(path, "w") as fh:
        fh.write(text)
    return path


_TEMPLATE = '''#!/usr/bin/env python3
"""CadQuery assembly of a STEP file with the mates mateqa predicted as constraints.

Run:  python this_script.py [--step FILE] [--json OUT] [--perturb MM] [--list]

DATA below holds everything about the assembly: its name, the STEP file, the parts and the
constraints (mateqa's sidecar JSON beside this script has the same and more).

Parts come from the STEP file (found by volume and centroid), each in its own frame at its
placement; each predicted mate with a CAD face mate behind it constrains that face geometry
(coincident: Axis + PointInPlane; concentric: Axis + PointOnLine); the largest part of each
constrained group is Fixed, and holds keep the motions the mates leave free (a joint's angle
or travel) where the file has them. The solve must give back the file's placements (within
TOL_MM and TOL_DEG) and satisfy every constraint. Mates that are not constraints here, with
the reason, are in DATA["unconstrained"] (--list prints them).
"""

import argparse
import json
import math
import sys
from pathlib import Path

import cadquery as cq
import numpy as np
from OCP.gp import gp_Trsf

DATA = json.loads(r"""
@DATA@
""")
TOL_MM = @TOL_MM@
TOL_DEG = @TOL_DEG@


def location(m):
    t = gp_Trsf()
    t.SetValues(*[float(v) for v in np.asarray(m, float).reshape(4, 4)[:3].ravel()])
    return cq.Location(t)


def matrix(loc):
    t = loc.wrapped.Transformation()
    m = np.eye(4)
    for i in range(3):
        for j in range(4):
            m[i, j] = t.Value(i + 1, j + 1)
    return m


def find_parts(step):
    """Each part's solid in the file frame, matched by volume and centroid."""
    solids = cq.importers.importStep(str(step)).solids().vals()
    taken, out = set(), {}
    for part in DATA["parts"]:
        best, best_d = None, math.inf
        for k, s in enumerate(solids):
            if k in taken or abs(s.Volume() - part["volume"]) > 1e-3 * max(part["volume"], 1.0):
                continue
            d = (s.Center() - cq.Vector(*part["centroid"])).Length
            if d < best_d:
                best, best_d = k, d
        if best is None or best_d > 1e-2:
            sys.exit(f"{step}: no solid matches part {part['name']!r} (the file changed?)")
        taken.add(best)
        out[part["key"]] = solids[best]
    return out


def marker(spec):
    if "point" in spec:
        return cq.Vertex.makeVertex(*spec["point"])
    if "line" in spec:
        p, d = (np.asarray(v, float) for v in spec["line"])
        return cq.Edge.makeLine(cq.Vector(*p), cq.Vector(*(p + 10.0 * d)))
    p, n = spec["plane"]
    return cq.Face.makePlane(10.0, 10.0, cq.Vector(*p), cq.Vector(*n))


def residual(c, locs):
    """The constraint's error at the solved placements: mm, or degrees for Axis."""
    def pt(key, p):
        return (locs[key] @ np.array([*p, 1.0]))[:3]

    def dr(key, d):
        return locs[key][:3, :3] @ np.asarray(d, float)

    a, b = c["a_marker"], c["b_marker"]
    if c["kind"] == "Axis":
        da = dr(c["a"], (a.get("plane") or a.get("line"))[1])
        db = dr(c["b"], (b.get("plane") or b.get("line"))[1])
        angle = math.degrees(math.acos(max(-1.0, min(1.0, float(da @ db)))))
        return abs(angle - c["param"])
    p = pt(c["a"], a["point"])
    base, direction = b.get("plane") or b.get("line")
    q, d = pt(c["b"], base), dr(c["b"], direction)
    if c["kind"] == "PointInPlane":
        return abs(float((p - q) @ d))
    off = p - q
    return float(np.linalg.norm(off - d * float(off @ d)))


def build(step, perturb=0.0):
    shapes = find_parts(step)
    assy = cq.Assembly(name=DATA["assembly"])
    starts = {}
    for part in DATA["parts"]:
        m = np.asarray(part["placement"], float).reshape(4, 4)
        local = shapes[part["key"]].moved(location(np.linalg.inv(m)))
        start = m.copy()
        if perturb and part["key"] in DATA["perturb_direction"]:
            start[:3, 3] += perturb * np.asarray(DATA["perturb_direction"][part["key"]])
        starts[part["key"]] = start
        assy.add(local, name=part["key"], loc=location(start))
    for key in DATA["anchors"]:
        assy.constrain(key, "Fixed")
    for c in DATA["constraints"]:
        assy.constrain(c["a"], marker(c["a_marker"]), c["b"], marker(c["b_marker"]), c["kind"],
                       c["param"]) if c["param"] is not None else assy.constrain(
            c["a"], marker(c["a_marker"]), c["b"], marker(c["b_marker"]), c["kind"])
    return assy, starts


def rotation_deg(a, b):
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, float(cos)))))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--step", default=DATA["step"], help="the assembly's STEP file")
    parser.add_argument("--json", help="write the solved placements and residuals here")
    parser.add_argument("--perturb", type=float, default=0.0,
                        help="start constrained parts this many mm off their placement")
    parser.add_argument("--list", action="store_true",
                        help="print the mates that are not constraints here, and stop")
    args = parser.parse_args(argv)
    if args.list:
        for line in DATA["unconstrained"]:
            print(repr(line))
        return 0
    assy, starts = build(Path(args.step), args.perturb)
    if DATA["constraints"]:
        assy.solve()
    locs = {k: matrix(assy.objects[k].loc) for k in (p["key"] for p in DATA["parts"])}
    constrained = {k for c in DATA["constraints"] for k in (c["a"], c["b"])}
    parts = []
    for part in DATA["parts"]:
        m = np.asarray(part["placement"], float).reshape(4, 4)
        got = locs[part["key"]]
        parts.append({"index": part["index"], "name": part["name"],
                      "status": "anchor" if part["key"] in DATA["anchors"] else
                      "constrained" if part["key"] in constrained else "unconstrained",
                      "placement": got.ravel().tolist(),
                      "start_offset_mm": float(np.linalg.norm(starts[part["key"]][:3, 3]
                                                              - m[:3, 3])),
                      "translation_mm": float(np.linalg.norm(got[:3, 3] - m[:3, 3])),
                      "rotation_deg": rotation_deg(got, m)})
    residuals = [{"kind": c["kind"], "mate": c["mate"], "a": c["a"], "b": c["b"],
                  "residual": residual(c, locs)} for c in DATA["constraints"]]
    ok = all(p["translation_mm"] <= TOL_MM and p["rotation_deg"] <= TOL_DEG for p in parts)
    held = all(r["residual"] <= (TOL_DEG if r["kind"] == "Axis" else TOL_MM) for r in residuals)
    out = {"assembly": DATA["assembly"], "perturb_mm": args.perturb, "parts": parts,
           "constraints": residuals, "reproduced": ok, "constraints_hold": held,
           "tolerance_mm": TOL_MM, "tolerance_deg": TOL_DEG}
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    print(f"{DATA['assembly']!r}: {len(parts)} parts, {len(residuals)} constraints, "
          f"placements reproduced: {ok}, constraints hold: {held}")
    return 0 if held else 1


if __name__ == "__main__":
    sys.exit(main())
'''
