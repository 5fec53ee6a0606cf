"""The workspace folder: where each artefact lives, and atomic reads and writes of them.

Layout (see DESIGN.md): ``catalog.parquet``, ``meshes/<part_id>.ply``,
``features/<part_id>.json``, ``voxels/<part_id>@<n>.npz``, ``mates/<assembly>.parquet``,
``scenes.parquet``, ``captures/<scene>.mcap``, ``inputs/<capture>/<part_id>.npz``,
``runs/<run_id>/``, ``library/`` (the generated sample library).
Every write goes to a temporary file in the same folder and is renamed into place, so a crash
never leaves a half-written artefact that a rerun would trust; files get the mode the umask
gives, so a shared workspace is readable by whom the umask allows. A write the machine stops
(no space left, a folder this user cannot write, an I/O error) raises ``MachineError``, which
no stage turns into a failed input: the stages catch ``OSError`` of their inputs, and this is
none of theirs.
"""

from __future__ import annotations

import json
import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np

from cadio.errors import MachineError
from cadio.records import Features, Mesh, VoxelGrid


@dataclass(frozen=True)
class Workspace:
    """Paths inside one workspace folder."""

    root: Path

    @property
    def catalog(self) -> Path:
        return self.root / "catalog.parquet"

    def mesh(self, part_id: str) -> Path:
        return self.root / "meshes" / f"{part_id}.ply"

    def features(self, part_id: str) -> Path:
        return self.root / "features" / f"{part_id}.json"

    def voxels(self, part_id: str, n: int) -> Path:
        return self.root / "voxels" / f"{part_id}@{n}.npz"

    def mates(self, assembly: str) -> Path:
        return self.root / "mates" / f"{assembly}.parquet"

    def capture(self, scene: str) -> Path:
        return self.root / "captures" / f"{scene}.mcap"

    @property
    def scenes(self) -> Path:
        return self.root / "scenes.parquet"

    def inputs(self, capture: str, instance: int | str) -> Path:
        """Learning inputs of one part instance seen in one capture (its instance id there: a
        capture may show one part twice): its completion examples (one
        ``<protocol>-<views>.npz`` each) and ``points.npz`` (600 observed points)."""
        return self.root / "inputs" / capture / str(instance)

    def checkpoints(self, stage: str) -> Path:
        """Checkpoints ``mateqa train`` wrote for a stage (``completion``, ``relations``)."""
        return self.root / "checkpoints" / stage

    def run_dir(self, run_id: str) -> Path:
        return self.root / "runs" / run_id

    @property
    def latest(self) -> Path:
        """``runs/latest``: a link to the newest finished run."""
        return self.root / "runs" / "latest"

    def mark_latest(self, run_id: str) -> None:
        """Point ``runs/latest`` at a run (a relative link, replaced atomically)."""
        tmp = self.latest.with_name(f".latest.{os.getpid()}")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(run_id, target_is_directory=True)
        try:
            os.replace(tmp, self.latest)
        except OSError:  # e.g. a folder of that name: no stray link is left beside it
            tmp.unlink(missing_ok=True)
            raise

    @property
    def library(self) -> Path:
        return self.root / "library"


def create_beside(path: Path, suffix: str = ".tmp") -> tuple[int, str]:
    """A new, empty, hidden file next to ``path`` for writing: (open descriptor, its path).

    Its mode is what the umask gives (0666 & ~umask), as for any file the user writes; the
    0600 of ``tempfile.mkstemp`` would survive the rename and keep every artefact from the
    other users of a shared workspace (a Dask worker's account, a QA engineer's).
    """
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}{suffix}"
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666), \
                str(tmp)
        except FileExistsError:
            continue
    raise FileExistsError(f"{path.parent}: no free temporary name beside {path.name}")


@contextmanager
def machine_faults(path: Path) -> Iterator[None]:
    """Within: an ``OSError`` of the machine (``MachineError.of``) met while writing ``path``
    is raised as ``MachineError`` naming ``path``; any other goes on as it is."""
    try:
        yield
    except OSError as exc:
        fault = MachineError.of(exc, path)
        if fault is None:
            raise
        raise fault from exc


@contextmanager
def atomic_write(path: Path, mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary file next to ``path``; rename it onto ``path`` only on success.

    Raises:
        MachineError: the machine stopped the write (no space, no permission, I/O).
    """
    with machine_faults(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = create_beside(path)
        try:
            with os.fdopen(fd, mode) as fh:
                yield fh
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Like ``atomic_write`` but yields a temporary path for libraries that want a filename."""
    with machine_faults(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = create_beside(path, path.suffix)  # libraries that check the suffix see it
        os.close(fd)
        try:
            yield Path(tmp)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise


def write_json(path: Path, data: Any) -> None:
    """Write ``data`` as indented JSON, atomically."""
    with atomic_write(path, "w") as fh:
        json.dump(data, fh, indent=1, sort_keys=True)


def write_features(path: Path, features: Features) -> None:
    write_json(path, features.to_dict())


def read_features(path: Path) -> Features:
    return Features.from_dict(json.loads(path.read_text()))


def features_of_mesh(mesh: Path) -> Features:
    """The features of the part whose mesh is ``mesh`` (``Workspace.mesh``), read from the same
    workspace: what a corpus's shots name of a part is its mesh's path."""
    return read_features(Workspace(mesh.parent.parent).features(mesh.stem))


def write_voxels(path: Path, grid: VoxelGrid) -> None:
    """Occupancy is bit-packed then compressed: 256^3 takes ~2 MB before compression."""
    with atomic_write(path) as fh:
        np.savez_compressed(
            fh, bits=np.packbits(grid.occupancy.ravel()), n=np.int64(grid.n),
            grid_to_part=grid.grid_to_part,
        )


def read_voxels(path: Path) -> VoxelGrid:
    with np.load(path) as z:
        n = int(z["n"])
        occ = np.unpackbits(z["bits"], count=n**3).astype(bool).reshape(n, n, n)
        return VoxelGrid(occupancy=occ, grid_to_part=np.asarray(z["grid_to_part"]))


def write_mesh(path: Path, mesh: Mesh) -> None:
    """Binary little-endian PLY, millimetres."""
    v = np.ascontiguousarray(mesh.vertices, dtype="<f8")
    t = np.ascontiguousarray(mesh.triangles, dtype="<i4")
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment units mm\n"
        f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(t)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    faces = np.empty(len(t), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    faces["n"] = 3
    faces["idx"] = t
    with atomic_write(path) as fh:
        fh.write(header)
        fh.write(v.tobytes())
        fh.write(faces.tobytes())


def read_mesh(path: Path) -> Mesh:
    """Read a PLY written by ``write_mesh``."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().splitlines()
    nv = int(next(h for h in header if h.startswith("element vertex")).split()[-1])
    nf = int(next(h for h in header if h.startswith("element face")).split()[-1])
    v = np.frombuffer(data, dtype="<f8", count=nv * 3, offset=end).reshape(nv, 3)
    faces = np.frombuffer(
        data, dtype=[("n", "u1"), ("idx", "<i4", (3,))], count=nf, offset=end + nv * 24
    )
    return Mesh(vertices=v.astype(np.float64), triangles=faces["idx"].astype(np.int64))
