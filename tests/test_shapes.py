"""Which parts are one shape: copies at other poses are; variants, and look-alikes with another
face count, are not; the key reads a workspace's catalog and features."""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd

from reports.shapes import GEOMETRY_COLUMNS, part_geometry, read_part_geometry, shape_keys


def _geometry(rows: list[tuple[str, float, float, int]]) -> pd.DataFrame:
    return pd.DataFrame([{"part_id": p, "source": f"{p}.step", "category": "c", "volume": v,
                          "area": a, "n_faces": f, "n_solids": 1} for p, v, a, f in rows],
                        columns=list(GEOMETRY_COLUMNS))


def test_parts_agreeing_within_the_tolerance_are_one_shape_and_the_rest_are_not() -> None:
    keys = shape_keys(_geometry([
        ("ball-1", 18.953184, 51.714707, 3), ("ball-2", 18.953184 * (1 + 1e-9), 51.714707, 3),
        ("longer", 18.953184 * 1.002, 51.714707 * 1.001, 3),  # a 0.2% longer variant
        ("other-faces", 18.953184, 51.714707, 4),  # same volume and area, another B-rep
        ("unknown-area", 18.953184, float("nan"), 3)]))
    assert keys["ball-1"] == keys["ball-2"] == "ball-1"  # the first by volume names the shape
    assert len({keys["ball-1"], keys["longer"], keys["other-faces"], keys["unknown-area"]}) == 4
    assert set(keys.index) == {"ball-1", "ball-2", "longer", "other-faces", "unknown-area"}


def test_the_key_does_not_depend_on_the_order_of_the_catalog() -> None:
    rows = [(f"p{k}", 10.0 + (k % 3), 5.0 + (k % 3), 6) for k in range(9)]
    forward, backward = shape_keys(_geometry(rows)), shape_keys(_geometry(rows[::-1]))
    assert forward.sort_index().equals(backward.sort_index())
    assert forward.nunique() == 3


def test_a_real_bearing_is_five_shapes_of_32_parts(shared_step_dir: Path,
                                                   tmp_path: Path) -> None:
    """The ball bearing holds 30 balls and cage pieces in three groups of ten identical
    solids, each at its own pose, and two rings: five shapes."""
    from cadio.cad.ingest import IngestConfig, ingest
    from cadio.sandbox import Limits

    library = tmp_path / "lib" / "bearings"
    library.mkdir(parents=True)
    shutil.copy(shared_step_dir / "linear-rotary-motion" / "kcl_ball-bearing.step", library)
    ingest(library.parent, tmp_path / "ws", IngestConfig(voxel_sizes=(16,),
                                                          limits=Limits(workers=1)))
    geometry = read_part_geometry(tmp_path / "ws" / "catalog.parquet")
    assert len(geometry) == 32 and (geometry["n_solids"] == 32).all()
    assert geometry["area"].gt(0).all()
    assert sorted(shape_keys(geometry).value_counts()) == [1, 1, 10, 10, 10]


def test_a_workspace_without_a_catalog_has_no_geometry(tmp_path: Path) -> None:
    assert read_part_geometry(tmp_path / "catalog.parquet").empty
    catalog = pd.DataFrame({"part_id": ["a", "b"], "status": ["ok", "failed"],
                            "source": ["a.step", "b.step"], "category": ["c", "c"],
                            "volume": [1.0, float("nan")], "n_faces": [6, 0],
                            "n_solids": [1, 0]})
    geometry = part_geometry(catalog, lambda part: 6.0)
    assert geometry["part_id"].tolist() == ["a"] and geometry["area"].tolist() == [6.0]
