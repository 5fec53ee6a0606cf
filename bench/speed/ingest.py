"""Benchmark: ``mateqa ingest`` of the real STEP files against the OpenCascade floor, in one run.

Command (from the repository root)::

    PYTHONPATH=$PWD .venv/bin/python bench/speed/ingest.py [STEP_DIR] [--workers 2] [--repeat 1]
        [--no-stages]

Printed, all from the same run so that the shared machine's load falls on both sides alike:

1. floor: a bare XDE read (``STEPCAFControl_Reader``) of every file and a ``BRepMesh`` of every
   solid with the project's deflection rule (``linear_deflection``), the files spread over
   WORKERS spawned processes, largest first; timed from spawning the processes to the last file;
2. product: ``mateqa ingest STEP_DIR --workspace FRESH --workers WORKERS`` end to end in a
   subprocess (catalog, meshes, features, voxels at the default sizes, report);
3. the ratio product / floor (the goal is at most 2);
4. per stage, in this process: what each step of a worker's job costs per part (CPU time).

Timings on a shared 2-core machine are noisy: ``--repeat`` runs floor and product alternately
and prints every pair and the median ratio. The CPU seconds of each side's processes (user +
system) are printed too: other people's load stretches wall time far more than CPU time.
"""

from __future__ import annotations

import argparse
import functools
import multiprocessing as mp
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DEFAULT_DIR = REPO.parent / "shared" / "data" / "step"


def _silence_stdout() -> None:
    """OpenCascade prints parser chatter to fd 1, as in the product's workers."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)


def floor_file(path: str, exact: bool = False) -> int:
    """Bare XDE read of one file and a BRepMesh of each of its solids; returns the solid count.

    With ``exact``, also the exact properties a bare OpenCascade program computes for the same
    ground truth: each solid's volume and centroid (``BRepGProp.VolumeProperties``), each
    face's area and centroid (``BRepGProp.SurfaceProperties``), both with the product's relative
    eps, and the solid's optimal box (``BRepBndLib.AddOptimal``).

    Imports stay inside: spawned floor workers load OCP and the deflection rule, nothing else.
    """
    from OCP.Bnd import Bnd_Box
    from OCP.BRepBndLib import BRepBndLib
    from OCP.BRepGProp import BRepGProp
    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.GProp import GProp_GProps
    from OCP.STEPCAFControl import STEPCAFControl_Reader
    from OCP.TCollection import TCollection_ExtendedString
    from OCP.TDF import TDF_LabelSequence
    from OCP.TDocStd import TDocStd_Document
    from OCP.TopAbs import TopAbs_FACE, TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer
    from OCP.XCAFDoc import XCAFDoc_DocumentTool, XCAFDoc_ShapeTool

    from cadio.cad.tessellate import linear_deflection
    from cadio.tolerances import DEFAULT_TOLERANCES as tol

    doc = TDocStd_Document(TCollection_ExtendedString("XmlOcaf"))
    reader = STEPCAFControl_Reader()
    reader.SetColorMode(True)
    reader.SetNameMode(True)
    reader.ReadFile(path)
    reader.Transfer(doc)
    roots = TDF_LabelSequence()
    XCAFDoc_DocumentTool.ShapeTool_s(doc.Main()).GetFreeShapes(roots)
    solids = 0
    for i in range(1, roots.Length() + 1):
        explorer = TopExp_Explorer(XCAFDoc_ShapeTool.GetShape_s(roots.Value(i)), TopAbs_SOLID)
        while explorer.More():
            solid = explorer.Current()
            BRepMesh_IncrementalMesh(solid, linear_deflection(solid, tol), False,
                                     tol.mesh_angular_rad, True)
            if exact:
                BRepGProp.VolumeProperties_s(solid, GProp_GProps(), 1e-6)
                faces = TopExp_Explorer(solid, TopAbs_FACE)
                while faces.More():
                    BRepGProp.SurfaceProperties_s(faces.Current(), GProp_GProps(), 1e-6)
                    faces.Next()
                BRepBndLib.AddOptimal_s(solid, Bnd_Box(), False, False)
            solids += 1
            explorer.Next()
    return solids


def _children_cpu() -> float:
    """CPU seconds of all finished (waited-for) descendants of this process."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def floor(files: list[Path], workers: int, exact: bool = False) -> tuple[float, float, int]:
    """(seconds, CPU seconds, solids) of the floor over ``workers`` processes, largest first."""
    order = sorted(files, key=lambda p: p.stat().st_size, reverse=True)
    cpu, start = _children_cpu(), time.perf_counter()
    pool = mp.get_context("spawn").Pool(workers, initializer=_silence_stdout)
    job = functools.partial(floor_file, exact=exact)
    solids = sum(pool.imap_unordered(job, [str(p) for p in order], chunksize=1))
    pool.close()
    pool.join()  # reaps the workers, so that their CPU time is counted
    return time.perf_counter() - start, _children_cpu() - cpu, solids


def product(root: Path, workers: int) -> tuple[float, float, int, int]:
    """(seconds, CPU seconds, rows, ok rows) of ``mateqa ingest`` into a fresh workspace."""
    import pandas as pd

    with tempfile.TemporaryDirectory() as ws:
        cmd = [sys.executable, "-m", "flows.cli", "ingest", str(root), "--workspace", ws,
               "--workers", str(workers)]
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        cpu, start = _children_cpu(), time.perf_counter()
        subprocess.run(cmd, cwd=REPO, env=env, check=True, capture_output=True)
        seconds, cpu = time.perf_counter() - start, _children_cpu() - cpu
        catalog = pd.read_parquet(Path(ws) / "catalog.parquet")
    return seconds, cpu, len(catalog), int((catalog["status"] == "ok").sum())


def compare(root: Path, workers: int, repeat: int) -> None:
    """Floor, product and exact floor alternately, ``repeat`` times; every run and the median
    ratios."""
    from cadio.cad.ingest import discover

    files = [f.path for f in discover(root) if f.path.is_file()]
    print(f"\nFloor vs product: {len(files)} files, {workers} worker processes; exact floor = "
          "floor + OpenCascade's volume, face and box properties of every solid")
    print(f"{'run':>3} {'floor s':>8} {'cpu s':>6} {'solids':>6} {'ingest s':>9} {'cpu s':>6} "
          f"{'rows':>5} {'ok':>4} {'ratio':>6} {'cpu ratio':>9} {'exact s':>8} {'cpu s':>6} "
          f"{'ratio':>6}")
    ratios, cpu_ratios, exact_ratios = [], [], []
    for run in range(1, repeat + 1):
        floor_s, floor_cpu, solids = floor(files, workers)
        ingest_s, ingest_cpu, rows, ok = product(root, workers)
        exact_s, exact_cpu, _ = floor(files, workers, exact=True)
        ratios.append(ingest_s / floor_s)
        cpu_ratios.append(ingest_cpu / floor_cpu)
        exact_ratios.append(ingest_s / exact_s)
        print(f"{run:>3} {floor_s:>8.2f} {floor_cpu:>6.1f} {solids:>6} {ingest_s:>9.2f} "
              f"{ingest_cpu:>6.1f} {rows:>5} {ok:>4} {ratios[-1]:>6.2f} {cpu_ratios[-1]:>9.2f} "
              f"{exact_s:>8.2f} {exact_cpu:>6.1f} {exact_ratios[-1]:>6.2f}")
    print(f"median ratio ingest / floor: {statistics.median(ratios):.2f} wall, "
          f"{statistics.median(cpu_ratios):.2f} CPU (goal: at most 2); ingest / exact floor: "
          f"{statistics.median(exact_ratios):.2f} wall")


def stages(root: Path) -> None:
    """Per-stage CPU cost of a worker's job, in this process, ms per part."""
    from cadio.cad.faces import indexed_faces
    from cadio.cad.features import extract_features
    from cadio.cad.ingest import IngestConfig, discover
    from cadio.cad.solid_props import part_integrals
    from cadio.cad.step import read_step
    from cadio.cad.tessellate import MASS_PROPS_REL_EPS, tessellate
    from cadio.cad.voxels import voxelize_sizes
    from cadio.workspace import write_features, write_mesh, write_voxels

    sizes, tol = IngestConfig().voxel_sizes, IngestConfig().tolerances
    seconds: dict[str, float] = defaultdict(float)
    parts = 0

    def timed(name: str, fn, *args):  # type: ignore[no-untyped-def]
        t = time.process_time()
        out = fn(*args)
        seconds[name] += time.process_time() - t
        return out

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        for found in discover(root):
            for solid in timed("read", read_step, found.path):
                faces = indexed_faces(solid.shape)
                mass = timed("mass", part_integrals, solid.shape, faces, MASS_PROPS_REL_EPS)
                mesh = timed("tessellate", tessellate, solid.shape)
                features = timed("features", extract_features, solid.shape, tol, mass)
                grids = timed("voxels", voxelize_sizes, mesh, sizes)
                timed("write", write_mesh, out / "m.ply", mesh)
                timed("write", write_features, out / "f.json", features)
                for n, grid in zip(sizes, grids, strict=True):
                    timed("write", write_voxels, out / f"v{n}.npz", grid)
                parts += 1
    total = sum(seconds.values())
    print(f"\nPer stage, CPU in this process ({parts} parts; voxels at {sizes}; mass = volume, "
          "centroid and per-face areas, features = recognition, groups, box)")
    print(f"{'stage':<12} {'seconds':>9} {'ms/part':>9}")
    for name, s in [*seconds.items(), ("total", total)]:
        print(f"{name:<12} {s:>9.2f} {1000 * s / parts:>9.1f}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", nargs="?", type=Path, default=DEFAULT_DIR)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--no-stages", action="store_true", help="skip the per-stage table")
    args = parser.parse_args()
    if not args.root.is_dir():
        print(f"no STEP folder at {args.root}", file=sys.stderr)
        return 1
    compare(args.root.resolve(), args.workers, args.repeat)
    if not args.no_stages:
        stages(args.root)
    return 0


if __name__ == "__main__":
    sys.exit(main())
