"""Every real STEP file in ../shared/data/step ingests, with B-rep-consistent geometry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cadio.cad.ingest import IngestConfig, ingest
from cadio.sandbox import Limits
from cadio.workspace import Workspace, read_features, read_voxels


@pytest.fixture(scope="module")
def real(shared_step_dir: Path, tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    ws = Workspace(tmp_path_factory.mktemp("real"))
    cfg = IngestConfig(voxel_sizes=(32,), limits=Limits(workers=2))
    return ws, ingest(shared_step_dir, ws.root, cfg)


def test_every_real_file_ingests(real, manifest: pd.DataFrame) -> None:  # type: ignore[no-untyped-def]
    _, catalog = real
    bad = catalog[catalog["status"] != "ok"]
    assert bad.empty, bad[["source", "error"]].to_string()
    per_file = catalog.groupby("source").size()
    for relative, row in manifest.iterrows():
        source = next(s for s in per_file.index if s.endswith(str(relative)))
        assert per_file[source] == row["n_solids"], relative


def test_categories_come_from_folders(real) -> None:  # type: ignore[no-untyped-def]
    _, catalog = real
    for category, source in zip(catalog["category"], catalog["source"], strict=True):
        assert Path(source).parent.name == category


def test_mesh_volumes_agree_with_brep(real) -> None:  # type: ignore[no-untyped-def]
    _, catalog = real
    err = catalog["volume_rel_error"].abs()
    whole = catalog["mesh_missing_faces"] == 0
    # 0.1 mm chordal deviation: within 2% on every fully meshed part, far tighter on most.
    assert (err[whole] < 0.02).all(), catalog.loc[whole & (err >= 0.02), ["source", "name"]]
    assert err.median() < 0.005
    # A face OCCT cannot mesh (one in abc_00509765) is reported, never silently accepted.
    holed = catalog[~whole]
    assert len(holed) <= 2
    assert all("could not be meshed" in w for w in holed["warning"])


def _one(catalog: pd.DataFrame, name: str) -> pd.Series:
    return catalog[catalog["source"].str.endswith(name)].iloc[0]


@pytest.mark.parametrize("name", ["kcl_socket-head-cap-screw.step", "occt_xr1-tc-blt.stp",
                                  "partcad_bolt_M8x30.step"])
def test_bolt_principal_axis_is_its_shank(real, name: str) -> None:  # type: ignore[no-untyped-def]
    ws, catalog = real
    row = _one(catalog, name)
    f = read_features(ws.features(row["part_id"]))
    assert f.principal_axis is not None
    extent = f.bbox_max - f.bbox_min
    assert abs(f.principal_axis.direction[int(np.argmax(extent))]) > 0.999


@pytest.mark.parametrize("name", ["kcl_hex-nut.step", "occt_xr1-tc-nut.stp"])
def test_nut_principal_axis_is_its_bore(real, name: str) -> None:  # type: ignore[no-untyped-def]
    ws, catalog = real
    row = _one(catalog, name)
    f = read_features(ws.features(row["part_id"]))
    assert f.principal_axis is not None
    extent = f.bbox_max - f.bbox_min
    assert abs(f.principal_axis.direction[int(np.argmin(extent))]) > 0.999
    axis = f.principal_axis
    offset = f.centroid - axis.point
    off_axis = offset - np.dot(offset, axis.direction) * axis.direction
    assert np.linalg.norm(off_axis) < 0.05 * float(extent.max())


def test_voxel_grids_cover_the_part(real) -> None:  # type: ignore[no-untyped-def]
    ws, catalog = real
    row = _one(catalog, "kcl_hex-nut.step")
    grid = read_voxels(ws.voxels(row["part_id"], 32))
    centre = grid.grid_to_part @ np.array([15.5, 15.5, 15.5, 1.0])
    bbox_centre = (np.array(row["bbox_min"]) + np.array(row["bbox_max"])) / 2
    assert np.allclose(centre[:3], bbox_centre, atol=1e-6)
    assert grid.occupancy.sum() * grid.voxel_size**3 == pytest.approx(row["volume"], rel=0.2)
