"""Which parts are the same shape, and which file each came from.

A library repeats shapes: one rack carries 63 identical teeth, a bearing 28 identical balls, an
assembly 24 copies of one wheel part. Each copy is a part (its own id, pose and score), so a
mean over parts weighs a shape by how often it repeats; the completion headline
(``reports.headline``) weighs every distinct shape once instead.

Two parts are one shape when their ingest geometry agrees: the B-rep volume and surface area
within ``ShapeConfig.rel_tol`` of each other, and the same number of B-rep faces. All three are
unchanged by a rigid motion (copies sit at other poses; a bounding box or a tessellation is
not: the catalog's meshed volume of one ball differs by 0.1% between its copies), and
together they separate real parts that differ at all (two parts of equal volume rarely share
their area to four digits and their face count too). A mirrored copy is the same shape by this
key; for completing a solid from a view it is. Pure pandas and the standard library.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

GEOMETRY_COLUMNS = ("part_id", "source", "category", "volume", "area", "n_faces", "n_solids")


@dataclass(frozen=True)
class ShapeConfig:
    """How close two parts' volumes and areas must be to be one shape."""

    # Copies of one solid agree to about 1e-9 (OpenCascade's integration at their poses); a
    # real variant (a 0.1 mm longer pin) differs by more than 1e-3.
    rel_tol: float = 1e-4


DEFAULT_SHAPES = ShapeConfig()


def part_geometry(catalog: pd.DataFrame, area_of: Callable[[str], float]) -> pd.DataFrame:
    """Each ingested part's source file, category and shape signature (``GEOMETRY_COLUMNS``).

    Args:
        catalog: the workspace catalog (``cadio.catalog.read_catalog``); its ``ok`` rows count.
        area_of: part id -> its B-rep surface area, mm^2 (NaN where unknown:
            ``features_area``).
    """
    ok = catalog[catalog["status"] == "ok"].drop_duplicates("part_id")
    frame = pd.DataFrame({
        "part_id": ok["part_id"].astype(str), "source": ok["source"].astype(str),
        "category": ok["category"].astype(str), "volume": ok["volume"].astype(float),
        "area": [float(area_of(str(p))) for p in ok["part_id"]],
        "n_faces": ok["n_faces"].astype("int64"), "n_solids": ok["n_solids"].astype("int64")})
    return frame.reset_index(drop=True)[list(GEOMETRY_COLUMNS)]


def features_area(features_dir: Path) -> Callable[[str], float]:
    """part id -> the ``area`` of ``features_dir/<part_id>.json`` (NaN where absent)."""
    def area(part_id: str) -> float:
        path = Path(features_dir) / f"{part_id}.json"
        if not path.is_file():
            return math.nan
        return float(json.loads(path.read_text()).get("area", math.nan))
    return area


def read_part_geometry(catalog_path: Path) -> pd.DataFrame:
    """``part_geometry`` of a workspace's catalog, areas from its ``features/`` beside it
    (empty, with its columns, without a catalog)."""
    if not Path(catalog_path).is_file():
        return pd.DataFrame(columns=list(GEOMETRY_COLUMNS))
    from cadio.catalog import read_catalog

    return part_geometry(read_catalog(Path(catalog_path)),
                         features_area(Path(catalog_path).parent / "features"))


def shape_keys(geometry: pd.DataFrame, cfg: ShapeConfig = DEFAULT_SHAPES) -> pd.Series:
    """part id -> its shape: the part id of the first part (by volume) it shares a shape with.

    Parts are grouped, in order of volume, with the first part of a group whose face count is
    theirs and whose volume and area lie within ``cfg.rel_tol`` (relative) of theirs. A part
    without a volume or area is a shape of its own.
    """
    ordered = geometry.sort_values(["volume", "part_id"], kind="stable")
    firsts: list[tuple[float, float, int, str]] = []
    keys: dict[str, str] = {}
    for part, volume, area, faces in zip(ordered["part_id"], ordered["volume"], ordered["area"],
                                         ordered["n_faces"], strict=True):
        match = next((k for v, a, f, k in reversed(firsts) if f == faces
                      and _close(v, volume, cfg.rel_tol) and _close(a, area, cfg.rel_tol)), None)
        if match is None:
            match = str(part)
            firsts.append((float(volume), float(area), int(faces), match))
        keys[str(part)] = match
    return pd.Series(keys, name="shape", dtype="str").rename_axis("part_id")


def _close(a: float, b: float, rel_tol: float) -> bool:
    """Within ``rel_tol`` of the larger; never for a NaN."""
    return math.isclose(a, b, rel_tol=rel_tol, abs_tol=0.0)
