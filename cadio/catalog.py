"""The part catalog: one row per part (solid) or per file that yielded none, in parquet.

``CatalogRow`` is the typed record the ingest stage produces (see DESIGN.md): ``part_id``
(content hash of the file plus the solid index), ``category`` (the folder name), ``source``
(the file), ``status`` (``ok``, ``failed`` or ``skipped``), ``error`` (the reason, empty when
ok), and the geometry summary of each solid. The catalog file is those rows as a table.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cadio.workspace import atomic_path

if TYPE_CHECKING:
    import pandas as pd

STATUSES = ("ok", "failed", "skipped")


@dataclass(frozen=True)
class CatalogRow:
    """One part of the catalog (or one file that yielded no part). Lengths mm, volumes mm^3."""

    part_id: str = ""
    category: str = ""
    source: str = ""
    source_sha256: str = ""
    solid_index: int = -1  # -1 for a file without a solid
    n_solids: int = 0
    name: str = ""
    colour: str = ""  # sRGB "#rrggbb" or ""
    path_in_assembly: str = ""
    placement: tuple[float, ...] | None = None  # 16 floats, row-major 4x4, mm
    bbox_min: tuple[float, ...] | None = None  # 3 floats, mm
    bbox_max: tuple[float, ...] | None = None
    volume: float = math.nan  # B-rep volume
    mesh_volume: float = math.nan  # tessellated volume
    volume_rel_error: float = math.nan  # (mesh - brep) / brep
    n_triangles: int = 0
    n_faces: int = 0
    mesh_missing_faces: int = 0  # faces OCCT could not triangulate (holes in the mesh)
    voxel_sizes: tuple[int, ...] | None = None  # grid sizes written under voxels/
    status: str = "failed"
    error: str = ""
    warning: str = ""  # set on ok rows whose derived data is less trustworthy
    seconds: float = 0.0
    config_key: str = ""
    cached: bool = False

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @classmethod
    def from_record(cls, record: Mapping[str, Any]) -> CatalogRow:
        """A row from a catalog frame record (``read_catalog(...).to_dict("records")``)."""
        values: dict[str, Any] = {}
        for f in fields(cls):
            if f.name in record:
                values[f.name] = _typed(f.name, record[f.name])
        return cls(**values)


_TYPES = {"solid_index": int, "n_solids": int, "n_triangles": int, "n_faces": int,
          "mesh_missing_faces": int, "volume": float, "mesh_volume": float,
          "volume_rel_error": float, "seconds": float, "cached": bool}
_LIST_COLUMNS = ("placement", "bbox_min", "bbox_max", "voxel_sizes")
# Column -> pandas dtype; the order is the order written.
COLUMNS: dict[str, str] = {
    f.name: ("object" if f.name in _LIST_COLUMNS else
             {int: "int64", float: "float64", bool: "bool"}.get(_TYPES.get(f.name, str), "string"))
    for f in fields(CatalogRow)
}


def _typed(name: str, value: Any) -> Any:
    """A frame value as the field's Python type (lists as tuples, missing text as "")."""
    import pandas as pd  # here, not at the top: CAD worker processes build rows, never frames

    if name in _LIST_COLUMNS:
        return None if value is None else tuple(value)
    kind = _TYPES.get(name, str)
    if value is None or value is pd.NA:
        return "" if kind is str else (math.nan if kind is float else kind())
    return kind(value)


def to_frame(rows: Sequence[CatalogRow]) -> pd.DataFrame:
    """Rows as a typed DataFrame, in catalog column order."""
    import pandas as pd

    frame = pd.DataFrame([asdict(r) for r in rows], columns=list(COLUMNS))
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
    import pandas as pd

    if not path.exists():
        return to_frame([])
    frame = pd.read_parquet(path)
    for name, dtype in COLUMNS.items():
        if dtype == "object" and name in frame:
            frame[name] = [json.loads(v) if isinstance(v, str) else v for v in frame[name]]
    return frame


def catalog_rows(frame: pd.DataFrame) -> list[CatalogRow]:
    """The rows of a catalog frame as records."""
    return [CatalogRow.from_record(r) for r in frame.to_dict("records")]


def _plain(value: Any) -> Any:
    if value is None:
        return None
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
