"""The part catalog: one row per part (solid) or per file that yielded none, in parquet.

Columns (see DESIGN.md): ``part_id`` (content hash of the file plus the solid index),
``category`` (the folder name), ``source`` (the file), ``status`` (``ok``, ``failed`` or
``skipped``), ``error`` (the reason, empty when ok), and the geometry summary of each solid.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from cadio.workspace import atomic_path

STATUSES = ("ok", "failed", "skipped")

# Column -> pandas dtype; the order is the order written.
COLUMNS: dict[str, str] = {
    "part_id": "string",
    "category": "string",
    "source": "string",
    "source_sha256": "string",
    "solid_index": "int64",
    "n_solids": "int64",
    "name": "string",
    "colour": "string",
    "path_in_assembly": "string",
    "placement": "object",  # 16 floats, row-major 4x4, mm
    "bbox_min": "object",  # 3 floats, mm
    "bbox_max": "object",
    "volume": "float64",  # B-rep volume, mm^3
    "mesh_volume": "float64",  # tessellated volume, mm^3
    "volume_rel_error": "float64",  # (mesh - brep) / brep
    "n_triangles": "int64",
    "n_faces": "int64",
    "mesh_missing_faces": "int64",  # faces OCCT could not triangulate (holes in the mesh)
    "voxel_sizes": "object",  # grid sizes written under voxels/
    "status": "string",
    "error": "string",
    "warning": "string",  # set on ok rows whose derived data is less trustworthy
    "seconds": "float64",
    "config_key": "string",
    "cached": "bool",
}


def empty_row() -> dict[str, Any]:
    """A row with every column set to its neutral value."""
    return {
        "part_id": "", "category": "", "source": "", "source_sha256": "", "solid_index": -1,
        "n_solids": 0, "name": "", "colour": "", "path_in_assembly": "", "placement": None,
        "bbox_min": None, "bbox_max": None, "volume": float("nan"),
        "mesh_volume": float("nan"), "volume_rel_error": float("nan"), "n_triangles": 0,
        "n_faces": 0, "mesh_missing_faces": 0, "voxel_sizes": None, "status": "failed",
        "error": "", "warning": "", "seconds": 0.0,
        "config_key": "", "cached": False,
    }


def to_frame(rows: Sequence[dict[str, Any]]) -> pd.DataFrame:
    """Rows (dicts with the catalog columns) as a typed DataFrame, in catalog column order."""
    frame = pd.DataFrame([{**empty_row(), **r} for r in rows], columns=list(COLUMNS))
    for name, dtype in COLUMNS.items():
        if dtype != "object":
            frame[name] = frame[name].astype(dtype)
    return frame


def write_catalog(path: Path, frame: pd.DataFrame) -> None:
    """Write the catalog atomically; list columns are stored as JSON text for portability."""
    out = frame.copy()
    for name, dtype in COLUMNS.items():
        if dtype == "object":
            out[name] = [json.dumps(_plain(v)) for v in out[name]]
    with atomic_path(path) as tmp:
        out.to_parquet(tmp, index=False)


def read_catalog(path: Path) -> pd.DataFrame:
    """Read a catalog written by ``write_catalog``; an absent file gives an empty catalog."""
    if not path.exists():
        return to_frame([])
    frame = pd.read_parquet(path)
    for name, dtype in COLUMNS.items():
        if dtype == "object" and name in frame:
            frame[name] = [json.loads(v) if isinstance(v, str) else v for v in frame[name]]
    return frame


def _plain(value: Any) -> Any:
    if value is None:
        return None
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
