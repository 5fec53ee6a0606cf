"""Ingest a library of STEP files into the workspace: catalog, meshes, features, voxels.

Files are found recursively (``.step``/``.stp`` in any letter case), checked cheaply in this
process (not a regular file, size limit, a name that is not UTF-8, unreadable) and hashed; only
regular files are ever opened, so a named pipe or a link to a device never blocks the batch.
The real work, reading through OpenCascade and deriving geometry (``process_file``, the
worker's job), runs in crash-isolated worker processes (``cadio.sandbox``), largest file first
so that a big file does not run alone at the end. Every file found is accounted for by at least
one ``CatalogRow``: ok + failed + skipped = found. A rerun reuses the rows of files whose
content hash and configuration are unchanged.

This process never loads OCP or open3d (seconds of start-up on a small machine, while the
workers load them anyway): the worker's job at the bottom imports the CAD modules itself.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import stat
import time
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from cadio.catalog import CatalogRow, catalog_rows, read_catalog, to_frame, write_catalog
from cadio.errors import GeometryError, InputFileError, MachineError, WorkerError
from cadio.inputs import kind, open_regular, read_text
from cadio.sandbox import Job, Limits, run_isolated
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.workspace import Workspace, write_features, write_mesh, write_voxels

if TYPE_CHECKING:
    import pandas as pd
    from OCP.TopoDS import TopoDS_Shape

    from cadio.cad.solid_props import PartIntegrals
    from cadio.cad.step import StepSolid

log = logging.getLogger(__name__)

STEP_SUFFIXES = (".step", ".stp")
P = TypeVar("P")

# Bump when the derived artefacts change meaning, so cached rows are recomputed.
# 4: features carry the dominant plane direction; rational faces whose weights spread more than
# 4:1 are integrated with NumPy.
INGEST_VERSION = "4"


@dataclass(frozen=True)
class IngestJob:
    """One STEP file for an isolated worker: where it is, where its artefacts go, and how."""

    path: str
    category: str
    sha256: str
    workspace: str
    voxel_sizes: tuple[int, ...]
    tolerances: Tolerances
    config_key: str


IngestWorker = Callable[[IngestJob], list[CatalogRow]]


@dataclass(frozen=True)
class IngestConfig:
    """Knobs of the ingest stage."""

    # 32^3 feeds the CPU-sized completion network, 64^3 the paper's input; 256 is opt-in
    # (0.2-2 s and ~2 MB a part).
    voxel_sizes: tuple[int, ...] = (32, 64)
    max_file_mb: float = 200.0
    limits: Limits = field(default_factory=Limits)
    tolerances: Tolerances = DEFAULT_TOLERANCES
    # The job each worker runs per file (default ``process_file``); tests swap in a crashing one.
    worker: IngestWorker | None = None

    def key(self) -> str:
        """Hash of everything that changes the derived artefacts (not limits)."""
        blob = json.dumps([INGEST_VERSION, list(self.voxel_sizes), asdict(self.tolerances)],
                          sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:12]


@dataclass(frozen=True)
class Found:
    """A path found under the library root whose name ends in .step/.stp."""

    path: Path
    category: str


def discover(root: Path) -> list[Found]:
    """Every path under ``root`` named ``*.step``/``*.stp`` (any case), files or not; or, when
    ``root`` is a ``.csv`` file, the files it lists (see ``read_library_csv``).

    Directories and broken links with such names are returned too, so that they are reported
    rather than silently ignored; so are the folders that cannot be searched: one that cannot
    be read, and a link back to a folder above it (a loop, searched once). Links to folders
    are followed: a category folder may live elsewhere. The category is the first folder
    below ``root``; files lying directly in ``root`` take its own name (so pointing at one
    category folder works).

    Raises:
        InputFileError: ``root`` is neither a folder nor a readable library CSV.
    """
    root = Path(root)
    if root.suffix.lower() == ".csv" and root.is_file():
        return read_library_csv(root)
    if not root.is_dir():
        raise InputFileError(root, "library folder does not exist or is not a folder")
    found: list[Found] = []
    _search(root, root, [root.resolve()], found)
    return sorted(found, key=lambda f: f.path)


def _search(folder: Path, root: Path, above: list[Path], found: list[Found]) -> None:
    """The STEP paths under ``folder`` into ``found``, and the folders that cannot be searched
    (``above``: the real paths of the folders the search came through)."""
    try:
        entries = sorted(os.scandir(folder), key=lambda e: e.name)
    except OSError:  # unreadable: a row of its own, whose reason ``_screen`` gives
        found.append(Found(folder, _category(folder, root)))
        return
    for entry in entries:
        path = Path(entry.path)
        if path.suffix.lower() in STEP_SUFFIXES:
            found.append(Found(path, _category(path, root)))
        if not _is_folder(entry):
            continue
        real = path.resolve()
        if real in above or real in above[-1].parents:  # a link back up: searched once
            found.append(Found(path, _category(path, root)))
        else:
            _search(path, root, [*above, real], found)


def _is_folder(entry: os.DirEntry[str]) -> bool:
    try:
        return entry.is_dir()  # links followed
    except OSError:
        return False


def _category(path: Path, root: Path) -> str:
    """The first folder below ``root`` on the way to ``path``; ``root``'s name for a file
    lying in it."""
    rel = path.relative_to(root).parts
    return rel[0] if len(rel) > 1 or path.is_dir() else root.resolve().name


def read_library_csv(path: Path) -> list[Found]:
    """The files a library CSV lists: columns ``path`` (relative to the CSV's folder, or
    absolute) and ``category``, one row per STEP file; listed files that are missing are
    returned too, so that the report accounts for them. A file listed again is read once (the
    first line wins; a warning names both lines). A byte-order mark, as spreadsheets save, is
    allowed.

    Raises:
        InputFileError: the CSV cannot be read, is empty, lacks a column, or has a row without
            a category (the line is named).
    """
    import csv
    import io

    text = read_text(path, "library CSV")
    if not text.strip():
        raise InputFileError(path, "library CSV is empty (it needs a header line path,category)")
    try:
        reader = csv.DictReader(io.StringIO(text, newline=""))
        rows = list(reader)
    except csv.Error as exc:
        raise InputFileError(path, f"library CSV cannot be read: {exc}") from exc
    header = [c.strip() for c in reader.fieldnames or ()]
    if not {"path", "category"} <= set(header):
        raise InputFileError(path, f"library CSV needs the columns path and category, has "
                             f"{', '.join(map(repr, header)) or 'none'}")
    reader.fieldnames = header
    return _listed(path, rows)


def _listed(path: Path, rows: list[dict[str, str]]) -> list[Found]:
    """Found files of the CSV's rows (line 2 is the first), each file once."""
    found: list[Found] = []
    first: dict[Path, int] = {}
    for line, row in enumerate(rows, start=2):
        name, category = (row.get("path") or "").strip(), (row.get("category") or "").strip()
        if not name:
            continue
        if not category:
            raise InputFileError(path, f"line {line}: {name} has no category")
        file = path.parent / name
        seen = first.setdefault(file.resolve(), line)
        if seen != line:
            log.warning("%s: line %d lists %s again (first on line %d): read once", path, line,
                        name, seen)
            continue
        found.append(Found(file, category))
    return found


def file_sha256(path: Path, max_bytes: int | None = None) -> str:
    """Hex SHA-256 of a regular file's bytes, read in 1 MiB blocks.

    Raises:
        InputFileError: not a regular file (a pipe or a device is never read), or longer than
            ``max_bytes`` (it may have grown since its size was checked).
        OSError: it cannot be opened or read.
    """
    digest, left = hashlib.sha256(), max_bytes
    with open_regular(path) as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
            if left is not None:
                left -= len(block)
                if left < 0:
                    raise InputFileError(path, f"grew beyond {(max_bytes or 0) / 1e6:g} MB "
                                         "while read")
    return digest.hexdigest()


def ingest(root: Path, workspace: Path, cfg: IngestConfig | None = None,
           on_file: Callable[[str], None] | None = None,
           categories: Collection[str] | None = None) -> pd.DataFrame:
    """Ingest every STEP file under ``root`` into ``workspace`` and write its catalog.

    Args:
        on_file: called with each file's path once it is done (for progress bars).
        categories: only the files of these categories (None: every one).

    Returns:
        The catalog (also written to ``workspace/catalog.parquet``).

    Raises:
        InputFileError: ``root`` is not a folder.
        MachineError: the workspace cannot be written (no space, no permission); no row of
            the files is kept as failed.
    """
    cfg = cfg or IngestConfig()
    ws = Workspace(Path(workspace))
    previous = read_catalog(ws.catalog)
    found = [f for f in discover(root) if categories is None or f.category in categories]
    rows = ingest_files(found, ws.root, cfg, previous, on_file)
    frame = to_frame(rows)
    write_catalog(ws.catalog, frame)
    return frame


def ingest_files(
    found: Sequence[Found], workspace: Path, cfg: IngestConfig, previous: pd.DataFrame | None,
    on_file: Callable[[str], None] | None = None,
) -> list[CatalogRow]:
    """Catalog rows for ``found``: reused from ``previous``, rejected cheaply, or processed.

    Duplicates (same bytes as an earlier file in ``found``) are skipped with a reason.
    """
    ws = Workspace(Path(workspace))
    cached = _cached_rows(previous, cfg.key())
    done = on_file or (lambda path: None)
    rows: list[CatalogRow] = []
    jobs: list[Job[IngestJob]] = []
    for item in found:
        row, sha = _screen(item, cfg)
        if row is not None:
            rows.append(row)
        elif sha in cached:
            rows.extend(replace(r, source=str(item.path), category=item.category, cached=True)
                        for r in cached[sha])
        else:
            jobs.append(Job(str(item.path), _job(item, sha, ws, cfg)))
            continue
        done(str(item.path))
    rows.extend(_run_jobs(jobs, cfg, done))
    return mark_duplicates(rows)


def mark_duplicates(rows: Iterable[CatalogRow]) -> list[CatalogRow]:
    """Keep the first file (by path) of each content hash; later copies become skipped rows."""
    first: dict[str, str] = {}
    out: list[CatalogRow] = []
    for row in sorted(rows, key=lambda r: (r.source, r.solid_index)):
        sha, src = row.source_sha256, row.source
        if not sha or row.status == "skipped" or first.setdefault(sha, src) == src:
            out.append(row)
        elif row.solid_index <= 0 or row.part_id.endswith("-x"):
            base = CatalogRow(category=row.category, source=src, source_sha256=sha)
            out.append(_row(base, "skipped", f"duplicate of {first[sha]} (same content)"))
    return out


def _screen(item: Found, cfg: IngestConfig) -> tuple[CatalogRow | None, str]:
    """A final row for inputs that need no CAD kernel, else (None, content hash). Only regular
    files within the size limit are read (hashed), and only once each."""
    path = item.path
    base = CatalogRow(category=printable(item.category), source=printable(str(path)))
    if base.source != str(path) or base.category != item.category:
        return _row(base, "skipped", "the file or folder name is not valid UTF-8 (its bytes "
                    "are shown escaped): rename it to read it"), ""
    try:
        info = path.stat()
    except OSError as exc:
        return _row(base, "failed", f"cannot be read: {exc.strerror or exc}"), ""
    if stat.S_ISDIR(info.st_mode) and path.suffix.lower() not in STEP_SUFFIXES:
        return _folder_row(base, path), ""  # a folder discover could not search
    if stat.S_ISDIR(info.st_mode):
        return _row(base, "skipped", "is a directory, not a STEP file"), ""
    if not stat.S_ISREG(info.st_mode):
        return _row(base, "skipped", f"is {kind(info.st_mode)}, not a regular file: not "
                    "read"), ""
    size_mb = info.st_size / 1e6
    if size_mb > cfg.max_file_mb:
        reason = f"file is {size_mb:.1f} MB, over the {cfg.max_file_mb:g} MB limit"
        return _row(base, "skipped", reason), ""
    try:
        sha = file_sha256(path, int(cfg.max_file_mb * 1e6))
    except InputFileError as exc:
        return _row(base, "skipped", exc.reason), ""
    except OSError as exc:
        return _row(base, "failed", f"cannot be read: {exc.strerror or exc}"), ""
    return None, sha


def _folder_row(base: CatalogRow, path: Path) -> CatalogRow:
    """The row of a folder ``discover`` did not search: one it could not read, or a link back
    to a folder above it (it can be read: ``discover`` reports no other)."""
    try:
        os.scandir(path).close()
    except OSError as exc:
        return _row(base, "failed", f"folder cannot be read ({exc.strerror or exc}): its STEP "
                    "files are left out")
    return _row(base, "skipped", f"is a link to {path.resolve()}, a folder above it (a loop): "
                "searched once")


def printable(text: str) -> str:
    """``text`` as valid Unicode: bytes of a non-UTF-8 file name (surrogate escapes) shown as
    ``\\xff``; unchanged for every other name."""
    return os.fsencode(text).decode("utf-8", "backslashreplace")


def _row(base: CatalogRow, status: str, error: str) -> CatalogRow:
    # Rows without a solid are keyed by the path: two bad copies of one file stay distinct.
    pid = hashlib.sha256(base.source.encode()).hexdigest()
    return replace(base, part_id=f"{pid[:16]}-x", status=status, error=error)


def _cached_rows(previous: pd.DataFrame | None, key: str) -> dict[str, list[CatalogRow]]:
    """Rows of earlier runs by file hash: all ok, or failed with a deterministic reason."""
    out: dict[str, list[CatalogRow]] = {}
    if previous is None or previous.empty:
        return out
    for row in catalog_rows(previous):
        if row.config_key != key or row.status == "skipped" or not row.source_sha256:
            continue
        out.setdefault(row.source_sha256, []).append(row)
    return out


def _job(item: Found, sha: str, ws: Workspace, cfg: IngestConfig) -> IngestJob:
    return IngestJob(path=str(item.path), category=item.category, sha256=sha,
                     workspace=str(ws.root), voxel_sizes=tuple(cfg.voxel_sizes),
                     tolerances=cfg.tolerances, config_key=cfg.key())


def _run_jobs(jobs: Sequence[Job[IngestJob]], cfg: IngestConfig,
              done: Callable[[str], None]) -> list[CatalogRow]:
    rows: list[CatalogRow] = []
    for outcome in run_isolated(cfg.worker or process_file, largest_first(jobs), cfg.limits):
        job = outcome.job.payload
        done(job.path)
        if outcome.error is None:
            rows.extend(outcome.result or [])
            continue
        base = CatalogRow(category=job.category, source=job.path, source_sha256=job.sha256,
                          seconds=outcome.seconds, config_key=_failure_key(outcome.error, job))
        rows.append(_row(base, "failed", outcome.error.reason))
    return rows


def largest_first(jobs: Iterable[Job[P]]) -> list[Job[P]]:
    """Jobs largest file first, then by path (a stable order for reproducible logs).

    File size is the cheapest guess of the work a file holds; starting the big ones first
    keeps both workers busy until near the end instead of leaving one idle behind the last.
    """
    return sorted(jobs, key=lambda job: (-_size(Path(job.key)), job.key))


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:  # vanished since it was hashed: its worker reports that
        return 0


def _failure_key(error: InputFileError, job: IngestJob) -> str:
    """Deterministic input errors are cached; time-outs and crashes are retried next run."""
    return "" if isinstance(error, WorkerError) else job.config_key


# --------------------------------------------------------------- the worker's job


def part_id(sha256: str, index: int) -> str:
    """Stable id of solid ``index`` of the file with content hash ``sha256``."""
    return f"{sha256[:16]}-{index}"


def process_file(job: IngestJob) -> list[CatalogRow]:
    """Read one STEP file and write the geometry of each solid (runs in a worker process).

    Returns:
        One catalog row per solid.

    Raises:
        StepReadError: the file cannot be read into solids.
        MachineError: its artefacts cannot be written to the workspace (no space, no
            permission): the machine's fault, never the file's row.
    """
    from cadio.cad.solid_props import InstanceIntegrals
    from cadio.cad.step import read_step
    from cadio.cad.tessellate import MASS_PROPS_REL_EPS

    path = Path(job.path)
    solids = read_step(path)
    base = CatalogRow(category=job.category, source=str(path), source_sha256=job.sha256,
                      n_solids=len(solids), config_key=job.config_key)
    integrals = InstanceIntegrals(MASS_PROPS_REL_EPS)
    return [_process_solid(solid, base, job, integrals) for solid in solids]


def _process_solid(solid: StepSolid, base: CatalogRow, job: IngestJob,
                   integrate: Callable[[TopoDS_Shape], PartIntegrals]) -> CatalogRow:
    start = time.perf_counter()
    info = solid.info
    row = replace(base, part_id=part_id(job.sha256, info.index), solid_index=info.index,
                  name=info.name, colour=info.colour, path_in_assembly=info.path_in_assembly,
                  placement=tuple(info.placement.ravel().tolist()))
    try:
        row = _geometry(solid, row, job, integrate)
    except MachineError:  # the workspace's fault, not the solid's: never a failed row
        raise
    except Exception as exc:  # an OCCT failure on one solid must not lose the file's others
        row = replace(row, error=f"solid {info.index} ({info.name}): {type(exc).__name__}: {exc}")
    return replace(row, seconds=time.perf_counter() - start)


def _geometry(solid: StepSolid, row: CatalogRow, job: IngestJob,
              integrate: Callable[[TopoDS_Shape], PartIntegrals]) -> CatalogRow:
    """Mesh, features and voxels of one solid written to the workspace; the row, ok."""
    from cadio.cad.features import extract_features
    from cadio.cad.tessellate import mesh_volume, tessellate
    from cadio.cad.voxels import voxelize_sizes

    tol, ws, pid = job.tolerances, Workspace(Path(job.workspace)), row.part_id
    integrals = integrate(solid.shape)
    volume = integrals.volume
    if volume <= 0:
        reason = f"non-positive B-rep volume {volume:.3g} mm^3 (open or inverted shell)"
        raise GeometryError("solid", reason)
    mesh = tessellate(solid.shape, tol)
    features = extract_features(solid.shape, tol, integrals)
    write_mesh(ws.mesh(pid), mesh)
    write_features(ws.features(pid), features)
    grids = voxelize_sizes(mesh, job.voxel_sizes, margin=tol.grid_margin)
    for n, grid in zip(job.voxel_sizes, grids, strict=True):
        write_voxels(ws.voxels(pid, n), grid)
    mvol = mesh_volume(mesh)
    warning = (f"{mesh.missing_faces} face(s) could not be meshed: the mesh has holes and its "
               f"volume is off by {100 * (mvol - volume) / volume:.1f}%"
               if mesh.missing_faces else "")
    return replace(
        row, status="ok", bbox_min=tuple(features.bbox_min.tolist()),
        bbox_max=tuple(features.bbox_max.tolist()), volume=volume, mesh_volume=mvol,
        volume_rel_error=(mvol - volume) / volume, n_triangles=len(mesh.triangles),
        n_faces=features.n_faces, mesh_missing_faces=mesh.missing_faces, warning=warning,
        voxel_sizes=tuple(job.voxel_sizes))
