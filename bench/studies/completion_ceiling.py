"""What a perfect completion would give the relation stage: the ``completed`` input's ceiling.

The ``completed`` input reads each part's completion as the centres of its surface voxels
(``models.relation_inputs.completed.completed_clouds``), the evidence fitting planes and cylinders
to them with local PCA's normals. This asks how far that route can go, whatever the network: in the
captures of the held-out assemblies of a night's workspace, it swaps each part's completion for the
CAD's own surface (dense CAD samples of the part as placed, ``placed_cad_samples``) snapped to the
centres of an N^3 grid over the view's observed cube (the cube the completion predicts in,
``read_example(...).grid``): a completion that is right at every voxel, at resolution N. N = 0 keeps
the samples where they are (no grid at all). Beside them, ``network``: the shipped ``gan_lstm``'s
own completion, as a night reads it.

``--crossings``: beside ``network``, the same completion read at sub-voxel precision: the
points where its probabilities cross the decision threshold along the grid's edges
(``crossings``), where the night takes the centres of its surface voxels.

``--normals``: each voxel of a perfect completion also carries the mean exact normal of the CAD
samples in it (their faces' outward normals), as a completion that gives normals would; the
pair evidence then reads normals as it reads the ``truth`` input's.

For each variant it prints the F1 of every method on ``completed`` against the CAD mates of the
assemblies (``assembly_f1_table``, the nightly's ``assembly_mates.csv``), and writes them to
``--out`` (CSV). ``geometric`` reads any cloud as it comes; the networks were trained on the
shipped completion's 64^3 voxels, so only ``geometric`` shows what better clouds could give
without retraining.

Usage:
    .venv/bin/python bench/studies/completion_ceiling.py --workspace heldout/ws \
        [--grids 64 128 256 0] [--normals] [--crossings] [--out completion_ceiling.csv]

The workspace is a night's (``python -m models.training.heldout``, then ``mateqa nightly``), whose
captures, inputs, meshes and features it reads. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from cadio.capture.examples import OBSERVED, read_example
from cadio.capture.observe import CubeGrid
from cadio.catalog import read_catalog
from cadio.evidence.cad_samples import placed_cad_samples
from cadio.evidence.pairs import DEFAULT_PAIRS, PairView, capture_pairs
from cadio.recordings.mcap_io import read_scene_meta
from cadio.records import FloatArray
from cadio.workspace import Workspace, read_features, read_mesh
from models.evaluate import SHIPPED, load_models
from models.relate import SHIPPED_RELATIONS, load_relation_models, relate_views
from models.relation_inputs import INPUTS
from models.relation_inputs.completed import THRESHOLD, completion_builder, completions_of
from models.relation_inputs.partial import observed_clouds
from reports.relations import assembly_f1_table

SAMPLES = 20_000  # CAD samples per part before snapping: several per voxel at 256^3


def snapped(points: FloatArray, corner: FloatArray, rotation: FloatArray, side: float,
            n: int, normals: FloatArray | None = None) -> FloatArray:
    """The centres of the voxels of an n^3 grid over a cube (corner, rotation, side: world)
    that hold at least one of the points (world metres); n = 0: the points themselves. With
    ``normals`` (the points' unit normals), (m, 6): each centre and the mean normal of its
    points after it."""
    if n == 0:
        return points if normals is None else np.hstack([points, normals])
    ijk = np.floor((points - corner) @ rotation / side * n).astype(np.int64)
    inside = np.all((ijk >= 0) & (ijk < n), axis=1)
    cells, which = np.unique(ijk[inside], axis=0, return_inverse=True)
    centres = np.asarray(((cells + 0.5) / n * side) @ rotation.T + corner, dtype=np.float64)
    if normals is None:
        return centres
    which = which.ravel()
    mean = np.zeros((len(cells), 3))
    np.add.at(mean, which, normals[inside])
    length = np.linalg.norm(mean, axis=1, keepdims=True)
    # opposite normals in one voxel (both sides of a thin wall) cancel: keep the first one
    first = normals[inside][np.unique(which, return_index=True)[1]]
    return np.hstack([centres, np.where(length > 1e-6, mean / np.maximum(length, 1e-12), first)])


def perfect(capture: Path, ws: Workspace, n: int, normals: bool = False
            ) -> dict[tuple[str, int], FloatArray]:
    """(instance id as text, view) -> the CAD surface of that instance snapped to an n^3 grid
    over the view's observed cube, for every single observed view of the capture's parts; with
    ``normals``, each voxel's mean exact normal after its centre (``snapped``)."""
    meta = read_scene_meta(capture) or {}
    scale = float(meta.get("scale_m_per_mm", 0.0))
    out = {}
    for part in meta.get("parts", []):
        instance, pid = str(part["instance_id"]), str(part["part_id"])
        folder = ws.inputs(capture.stem, instance)
        files = sorted(folder.glob(f"{OBSERVED}-*.npz"))
        if not files:
            continue
        pose = np.asarray(part["pose_mm"], dtype=np.float64)
        cloud = np.asarray(placed_cad_samples(read_mesh(ws.mesh(pid)),
                                              read_features(ws.features(pid)), pid, pose,
                                              SAMPLES, scale), dtype=np.float64)
        for path in files:
            view = path.stem.removeprefix(f"{OBSERVED}-")
            if not view.isdigit():
                continue  # an example of several views
            grid = read_example(path).grid
            out[(instance, int(view))] = snapped(cloud[:, :3], grid.corner, grid.rotation,
                                                 grid.side, n,
                                                 cloud[:, 3:6] if normals else None)
    return out


def crossings(probs: FloatArray, grid_to_world: FloatArray, threshold: float = THRESHOLD
              ) -> FloatArray:
    """(m, 3) world: where an (n, n, n) probability field crosses ``threshold`` on the edges
    between neighbouring voxels, interpolated linearly (the vertices marching cubes would
    place), and the outer face of every voxel above it on the grid's border."""
    inside = probs > threshold
    n = probs.shape[0]
    found = []
    for axis in range(3):
        lo = tuple(slice(0, n - 1) if a == axis else slice(None) for a in range(3))
        hi = tuple(slice(1, n) if a == axis else slice(None) for a in range(3))
        cross = inside[lo] != inside[hi]
        ijk = np.argwhere(cross).astype(np.float64)
        p_lo, p_hi = probs[lo][cross], probs[hi][cross]
        ijk[:, axis] += (threshold - p_lo) / (p_hi - p_lo)
        found.append(ijk)
        for side, offset in ((0, -0.5), (n - 1, 0.5)):
            face = tuple(side if a == axis else slice(None) for a in range(3))
            rest = np.argwhere(inside[face]).astype(np.float64)
            found.append(np.insert(rest, axis, side + offset, axis=1))
    ijk = np.concatenate(found)
    return np.asarray(ijk @ grid_to_world[:3, :3].T + grid_to_world[:3, 3], dtype=np.float64)


def crossing_surface(probs: npt.NDArray[np.float32], grid: CubeGrid) -> FloatArray:
    """A completion's ``crossings`` over its observed grid (a
    ``models.relation_inputs.completed.Surface``)."""
    return crossings(probs.astype(np.float64), grid.grid_to_world(probs.shape[-1]))


def completed_only(views: list[PairView]) -> list[PairView]:
    """The views with their ``completed`` input and the observed points its networks read
    beside it (``RelationInput.observed_by``); the rows of ``completed`` are measured."""
    keep = {"completed", INPUTS.get("completed").observed_by}
    return [replace(v, points={k: p for k, p in v.points.items() if k in keep},
                    evidence={k: e for k, e in v.evidence.items() if k in keep},
                    centres={}) for v in views if "completed" in v.points]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, default=Path("heldout/ws"))
    parser.add_argument("--grids", type=int, nargs="*", default=[64, 128, 256, 0])
    parser.add_argument("--normals", action="store_true",
                        help="perfect completions carry their voxels' exact normals")
    parser.add_argument("--crossings", action="store_true",
                        help="also the network's completion read at its threshold crossings")
    parser.add_argument("--out", type=Path, default=Path("completion_ceiling.csv"))
    args = parser.parse_args()
    ws = Workspace(args.workspace)
    catalog = read_catalog(ws.catalog)
    categories = dict(zip(catalog["part_id"].astype(str), catalog["category"].astype(str),
                          strict=True))
    captures = sorted((ws.root / "captures").glob("assembly-*.mcap"))
    if not captures:
        sys.exit(f"{ws.root}: no assembly captures (run a night on it first)")
    relations = load_relation_models(SHIPPED_RELATIONS)
    completion = load_models(SHIPPED).models.get(("gan_lstm", OBSERVED))
    tables = []
    for grid in ["network", *(["crossings"] if args.crossings else []), *args.grids]:
        views: list[PairView] = []
        for capture in captures:
            done = (completions_of(capture, ws, completion) if grid == "network"
                    else completions_of(capture, ws, completion, crossing_surface)
                    if grid == "crossings" else perfect(capture, ws, int(grid), args.normals))
            views += capture_pairs(capture, ws, categories, DEFAULT_PAIRS, {
                "partial": observed_clouds, "completed": completion_builder(done)})
        kept = completed_only(views)
        rows = pd.DataFrame(relate_views(kept, relations))
        table = assembly_f1_table(rows[rows["input"] == "completed"])
        label = str(grid) if grid in ("network", "crossings") else (
            "exact" if grid == 0 else f"{grid}^3")
        label += " normals" if args.normals and grid not in ("network", "crossings") else ""
        print(f"\n{label}: {len(kept)} pair views")
        print(table.round(3).to_string())
        tables.append(table.rename(columns=lambda c, g=label: f"{g} {c}"))
    pd.concat(tables, axis=1).to_csv(args.out)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
