"""The sidecar JSON of an assembly: predicted mates and joints in the words CAD users know.

Parts are named as the STEP file names them (product name, product path, solid index in the
file's tree); joints carry their Onshape, FreeCAD and Fusion 360 names, as the mates parquet
does. ``mates.schema.json`` (JSON Schema 2020-12, shipped beside this module) is the contract;
every document is validated against it before it is written, and ``read_sidecar`` validates
what it reads.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

import jsonschema

from cadio.export.predictions import (
    AssemblyMates,
    FaceGeometry,
    PairMates,
    PartRef,
    RelationCall,
    finite,
)
from cadio.inspect.asbuilt import MateAsBuilt
from cadio.workspace import atomic_write

SCHEMA_ID = "mateqa.mates/1"


def schema() -> dict[str, Any]:
    """The JSON Schema of the sidecar."""
    text = resources.files("cadio.export").joinpath("mates.schema.json").read_text("utf-8")
    data: dict[str, Any] = json.loads(text)
    return data


def _part(p: PartRef) -> dict[str, Any]:
    return {"index": p.index, "name": p.name, "path": p.path, "part_id": p.part_id,
            "placement": [list(p.placement[i:i + 4]) for i in range(0, 16, 4)]}


def _ref(p: PartRef) -> dict[str, Any]:
    return {"index": p.index, "name": p.name, "path": p.path}


def _relation(c: RelationCall) -> dict[str, Any]:
    return {"relation": c.relation, "predicted": c.predicted, "confidence": finite(c.confidence),
            "p_true": finite(c.p_true), "views": c.views, "views_true": c.views_true,
            "cad": c.cad, "agrees": c.agrees}


def _face(f: FaceGeometry) -> dict[str, Any]:
    return {"relation": f.relation, "face_a": f.face_a, "face_b": f.face_b,
            "axis": list(f.axis), "origin": list(f.origin)}


def _pair(p: PairMates) -> dict[str, Any]:
    j = p.joint
    return {
        "a": _ref(p.a), "b": _ref(p.b), "status": p.status, "views": p.views,
        "relations": [_relation(c) for c in p.relations],
        "joint": {"predicted": j.predicted, "confidence": finite(j.confidence),
                  **j.cad_names(), "cad_kinematic": j.cad_kinematic,
                  "cad_suggested": j.cad_suggested, "agrees": j.agrees},
        "constraints": [_face(f) for f in p.constraints()],
    }


def _check(m: MateAsBuilt) -> dict[str, Any]:
    return {"index_a": m.index_a, "index_b": m.index_b, "face_a": m.face_a,
            "face_b": m.face_b, "relation": m.relation, "status": m.status,
            "reason": m.reason,
            "residuals": {r.name: {"value": finite(r.value), "threshold": finite(r.threshold)}
                          for r in m.residuals}}


def sidecar(mates: AssemblyMates) -> dict[str, Any]:
    """The sidecar document of an assembly (validated against the schema).

    Raises:
        jsonschema.ValidationError: the document breaks the schema (a bug, not bad input).
    """
    doc = {
        "schema": SCHEMA_ID, "assembly": mates.assembly, "category": mates.category,
        "source": {"path": mates.source, "sha256": mates.source_sha256},
        "run_id": mates.run_id, "status": mates.status, "reason": mates.reason,
        "models": dict(mates.models), "tolerances": dict(mates.tolerances),
        "parts": [_part(p) for p in mates.parts],
        "pairs": [_pair(p) for p in mates.pairs],
        "agreement": mates.agreement(),
        "as_built": {"verdict": mates.as_built_verdict(),
                     "mates": [_check(m) for m in mates.as_built]},
    }
    jsonschema.validate(doc, schema())
    return doc


def write_sidecar(path: Path, mates: AssemblyMates) -> Path:
    """Write the sidecar atomically; its path."""
    with atomic_write(path, "w") as fh:
        json.dump(sidecar(mates), fh, indent=1, ensure_ascii=False)
        fh.write("\n")
    return path


def read_sidecar(path: Path) -> dict[str, Any]:
    """A sidecar read back and validated.

    Raises:
        jsonschema.ValidationError: it breaks the schema.
    """
    doc: dict[str, Any] = json.loads(Path(path).read_text("utf-8"))
    jsonschema.validate(doc, schema())
    return doc
