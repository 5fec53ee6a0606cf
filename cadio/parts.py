"""Per-part geometry of one STEP file: the job each isolated ingest worker runs.

For every solid of the file: tessellate, compare the mesh volume with the B-rep volume, extract
B-rep features, voxelize at the configured sizes, and write mesh, features and voxels into the
workspace. Returns one catalog row per solid. A solid that fails gets a failed row of its own;
the other solids of the file still go through.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from cadio.catalog import empty_row
from cadio.errors import GeometryError
from cadio.features import extract_features
from cadio.step import StepSolid, read_step
from cadio.tessellate import brep_volume, mesh_volume, tessellate
from cadio.tolerances import Tolerances
from cadio.voxels import voxelize
from cadio.workspace import Workspace, write_features, write_mesh, write_voxels


def part_id(sha256: str, index: int) -> str:
    """Stable id of solid ``index`` of the file with content hash ``sha256``."""
    return f"{sha256[:16]}-{index}"


def process_file(payload: dict[str, Any]) -> list[dict[str, Any]]:
    """Read one STEP file and write the geometry of each solid (runs in a worker process).

    Args:
        payload: path, category, sha256, workspace, voxel_sizes, voxel_margin, tolerances,
            config_key (see ``cadio.ingest._payload``).

    Returns:
        One catalog row (dict) per solid.

    Raises:
        StepReadError: the file cannot be read into solids.
    """
    path = Path(payload["path"])
    solids = read_step(path)
    base = {
        "category": payload["category"], "source": str(path), "source_sha256": payload["sha256"],
        "n_solids": len(solids), "config_key": payload["config_key"],
    }
    return [_process_solid(solid, base, payload) for solid in solids]


def _process_solid(solid: StepSolid, base: dict[str, Any], payload: dict[str, Any]) -> dict:
    start = time.perf_counter()
    info = solid.info
    row = {
        **empty_row(), **base, "part_id": part_id(payload["sha256"], info.index),
        "solid_index": info.index, "name": info.name, "colour": info.colour,
        "path_in_assembly": info.path_in_assembly, "placement": info.placement.ravel().tolist(),
    }
    try:
        row.update(_geometry(solid, row["part_id"], payload))
        row["status"] = "ok"
    except Exception as exc:  # an OCCT failure on one solid must not lose the file's others
        row["error"] = f"solid {info.index} ({info.name}): {type(exc).__name__}: {exc}"
    row["seconds"] = time.perf_counter() - start
    return row


def _geometry(solid: StepSolid, pid: str, payload: dict[str, Any]) -> dict[str, Any]:
    tol = Tolerances(**payload["tolerances"])
    ws = Workspace(Path(payload["workspace"]))
    volume = brep_volume(solid.shape)
    if volume <= 0:
        reason = f"non-positive B-rep volume {volume:.3g} mm^3 (open or inverted shell)"
        raise GeometryError("solid", reason)
    mesh = tessellate(solid.shape, tol)
    features = extract_features(solid.shape, tol)
    write_mesh(ws.mesh(pid), mesh)
    write_features(ws.features(pid), features)
    for n in payload["voxel_sizes"]:
        write_voxels(ws.voxels(pid, n), voxelize(mesh, n, margin=payload["voxel_margin"]))
    mvol = mesh_volume(mesh)
    return {
        "bbox_min": features.bbox_min.tolist(), "bbox_max": features.bbox_max.tolist(),
        "volume": volume, "mesh_volume": mvol,
        "volume_rel_error": (mvol - volume) / volume if volume > 0 else float("nan"),
        "n_triangles": len(mesh.triangles), "n_faces": features.n_faces,
        "mesh_missing_faces": mesh.missing_faces,
        "warning": (f"{mesh.missing_faces} face(s) could not be meshed: the mesh has holes and "
                    f"its volume is off by {100 * (mvol - volume) / volume:.1f}%"
                    if mesh.missing_faces else ""),
        "voxel_sizes": list(payload["voxel_sizes"]),
    }
