"""Tests of cadio.cad.tessellate: watertight outward meshes whose volume matches the B-rep."""

from __future__ import annotations

from pathlib import Path

import build123d as bd
import numpy as np
import pytest
from OCP.gp import gp_Ax1, gp_Dir, gp_Pnt, gp_Trsf, gp_Vec
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS_Compound

from cadio.cad.tessellate import brep_volume, merge_vertices, mesh_volume, tessellate
from cadio.errors import GeometryError
from cadio.records import Mesh
from cadio.tolerances import DEFAULT_TOLERANCES

# Relative volume error allowed at the default tolerances (0.1 mm, 0.5 rad).
VOLUME_REL_TOL = 0.02
CATEGORIES = ("fasteners", "linear-rotary-motion")


def directed_edge_defects(mesh: Mesh) -> int:
    """Edges not used exactly once in each direction (0 for a closed, consistently wound mesh)."""
    t = mesh.triangles
    edges = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    fwd, fwd_count = np.unique(edges, axis=0, return_counts=True)
    back = {tuple(e) for e in edges[:, ::-1].tolist()}
    unmatched = sum(1 for e in fwd.tolist() if tuple(e) not in back)
    return int((fwd_count != 1).sum()) + unmatched


def test_box_mesh_is_closed_outward_and_exact() -> None:
    box = bd.Box(10, 20, 30).wrapped
    mesh = tessellate(box)
    assert len(mesh.vertices) == 8
    assert directed_edge_defects(mesh) == 0
    assert mesh_volume(mesh) == pytest.approx(6000.0, rel=1e-9)
    assert brep_volume(box) == pytest.approx(6000.0, rel=1e-9)


def test_location_and_reversal_are_applied() -> None:
    cyl = bd.Cylinder(5, 10).wrapped
    trsf = gp_Trsf()
    trsf.SetRotation(gp_Ax1(gp_Pnt(0, 0, 0), gp_Dir(1, 1, 0)), 0.7)
    trsf.SetTranslationPart(gp_Vec(100, -50, 7))
    moved = cyl.Moved(TopLoc_Location(trsf))
    base, mesh = tessellate(cyl), tessellate(moved)
    assert mesh.vertices.mean(axis=0) == pytest.approx([100, -50, 7], abs=0.5)
    assert mesh_volume(mesh) == pytest.approx(mesh_volume(base), rel=1e-6)
    inside_out = tessellate(moved.Reversed())
    assert mesh_volume(inside_out) == pytest.approx(-mesh_volume(base), rel=1e-6)
    assert brep_volume(moved.Reversed()) < 0


def test_no_faces_raises() -> None:
    with pytest.raises(GeometryError):
        tessellate(TopoDS_Compound())


def test_merge_vertices_joins_duplicates_and_drops_collapsed() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 1e-9], [0, 1, 0]], dtype=float)
    t = np.array([[0, 1, 2], [3, 2, 4]], dtype=np.int64)
    merged = merge_vertices(Mesh(v, t))
    assert len(merged.vertices) == 3
    assert merged.triangles.tolist() == [[0, 1, 2]]


@pytest.mark.shared
def test_volume_matches_brep_for_every_single_solid_part(
    shared_step_dir: Path, step_solids
) -> None:
    errors: dict[str, float] = {}
    defects: dict[str, int] = {}
    for category in CATEGORIES:
        for path in sorted((shared_step_dir / category).iterdir()):
            solids = step_solids(f"{category}/{path.name}")
            if len(solids) != 1:
                continue
            mesh = tessellate(solids[0], DEFAULT_TOLERANCES)
            exact = brep_volume(solids[0])
            errors[path.name] = abs(mesh_volume(mesh) - exact) / abs(exact)
            defects[path.name] = directed_edge_defects(mesh)
    assert len(errors) >= 20
    worst = max(errors, key=errors.__getitem__)
    assert errors[worst] <= VOLUME_REL_TOL, f"worst {worst}: {errors[worst]:.2%}"
    assert not any(defects.values()), {k: d for k, d in defects.items() if d}
