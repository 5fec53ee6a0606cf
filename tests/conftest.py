"""Shared pytest fixtures for mateqa's tests."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from cadio.sandbox import THREAD_VARIABLES

# Two test workers share two cores: each holds its numerical libraries (OpenMP, OpenBLAS, MKL:
# torch, numpy, open3d) to one thread, set before any of them loads (this module is read before
# the tests'), and what the tests start inherits it. (A training that ran at the libraries'
# two threads beside the other worker took 78 s in a CI run, 17 s alone.)
for _name in THREAD_VARIABLES:
    os.environ.setdefault(_name, "1")

SHARED_STEP_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "step"


@pytest.fixture(scope="session")
def shared_step_dir() -> Path:
    """The folder of real STEP files (../shared/data/step); skips the test when it is absent."""
    if not SHARED_STEP_DIR.is_dir():
        pytest.skip(f"real STEP files not found at {SHARED_STEP_DIR}")
    return SHARED_STEP_DIR


@pytest.fixture(scope="session")
def step_solids(shared_step_dir: Path):  # type: ignore[no-untyped-def]
    """A cached loader: relative path under the shared STEP folder -> its TopoDS_Solids.

    Reads with build123d (not the project's reader) so geometry tests stand on their own.
    """
    import build123d

    cache: dict[str, list] = {}

    def load(relative: str) -> list:
        if relative not in cache:
            shape = build123d.import_step(shared_step_dir / relative)
            cache[relative] = [s.wrapped for s in shape.solids()]
        return cache[relative]

    return load


@pytest.fixture(scope="session")
def manifest(shared_step_dir: Path):  # type: ignore[no-untyped-def]
    """MANIFEST.csv of the real STEP files, indexed by path relative to the step folder."""
    import pandas as pd

    frame = pd.read_csv(shared_step_dir.parent / "MANIFEST.csv")
    frame["relative"] = frame["file"].str.removeprefix("step/")
    return frame.set_index("relative")


@pytest.fixture(scope="session")
def trimmed_bspline():  # type: ignore[no-untyped-def]
    """A converter: solid -> a copy whose every surface is a B-spline wrapped in a
    ``Geom_RectangularTrimmedSurface``, as the KCL pipe stores its bevel cones (OCCT's
    ``GeomConvert_SurfToAnaSurf`` raises Standard_NullObject on such surfaces)."""
    from OCP.BRep import BRep_Builder, BRep_Tool
    from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert
    from OCP.Geom import Geom_RectangularTrimmedSurface
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_REVERSED
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopLoc import TopLoc_Location
    from OCP.TopoDS import TopoDS, TopoDS_Edge, TopoDS_Face, TopoDS_Shape

    from cadio.cad.faces import indexed_faces

    def pcurves(face: TopoDS_Face) -> list[tuple[TopoDS_Edge, tuple]]:
        """Each edge's curve(s) on the face: two on a seam, in the edge's orientation order."""
        out = []
        explorer = TopExp_Explorer(face, TopAbs_EDGE)
        while explorer.More():
            edge = TopoDS.Edge_s(explorer.Current())
            explorer.Next()
            c1 = BRep_Tool.CurveOnSurface_s(edge, face, 0.0, 0.0)
            if not BRep_Tool.IsClosed_s(edge, face):
                out.append((edge, (c1,)))
                continue
            c2 = BRep_Tool.CurveOnSurface_s(TopoDS.Edge_s(edge.Reversed()), face, 0.0, 0.0)
            out.append((edge, (c2, c1) if edge.Orientation() == TopAbs_REVERSED else (c1, c2)))
        return out

    def convert(shape: TopoDS_Shape) -> TopoDS_Shape:
        nurbs = BRepBuilderAPI_NurbsConvert(shape, True).Shape()
        builder = BRep_Builder()
        for face in indexed_faces(nurbs):
            loc = TopLoc_Location()
            surface = BRep_Tool.Surface_s(face, loc)
            wrapped = Geom_RectangularTrimmedSurface(surface, *surface.Bounds())
            for edge, curves in pcurves(face):  # pcurves are keyed by surface: move them over
                builder.UpdateEdge(edge, *curves, wrapped, loc, BRep_Tool.Tolerance_s(edge))
            builder.UpdateFace(face, wrapped, loc, BRep_Tool.Tolerance_s(face))
        return nurbs

    return convert


@pytest.fixture(scope="session")
def box_step(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small valid STEP part (a 20 x 10 x 5 mm box with a 4 mm hole), made with build123d.

    Written with a fixed header time stamp: its content hash, hence its part id and its
    train/val/test split, is the same in every session.
    """
    import build123d as bd

    from cadio.cad.step import write_step

    path = tmp_path_factory.mktemp("box") / "box.step"
    part = bd.Box(20, 10, 5) - bd.Cylinder(2, 5)
    part.label = "box"
    write_step(part, path)
    return path


@pytest.fixture(scope="session")
def pin_step(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A second small valid STEP part (a 4 x 12 mm pin), so that a night of ``box_step`` and
    this one has a pair to place: a night never pairs a part with itself."""
    import build123d as bd

    from cadio.cad.step import write_step

    path = tmp_path_factory.mktemp("pin") / "pin.step"
    part = bd.Cylinder(2, 12)
    part.label = "pin"
    write_step(part, path)
    return path


# Three small real parts in two categories and one small real assembly: enough for every stage
# of the nightly (scenes need two categories of single parts; the assembly gives CAD mates).
# Files the shipped checkpoints never trained on (their corpus holds these out), so that a
# night scores them: a night leaves out every part a checkpoint lists among its training parts.
SMALL_LIBRARY = {
    "fasteners": ["fasteners/kcl_washer.step", "fasteners/kcl_socket-head-cap-screw.step"],
    "couplings": ["brakes-clutches-couplings/spot_Shaft_Coupling.step"],
    "assemblies": ["assemblies/abc_00509609_arbor-press.step"],
}


@pytest.fixture(scope="session")
def small_library(shared_step_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A library folder of real STEP files (copied from ../shared), by category."""
    import shutil

    root = tmp_path_factory.mktemp("small-library")
    for category, files in SMALL_LIBRARY.items():
        (root / category).mkdir()
        for name in files:
            shutil.copy(shared_step_dir / name, root / category / Path(name).name)
    return root


@pytest.fixture(scope="session")
def parts_library(small_library: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``small_library`` without its assembly: the parts of two categories, for a night whose
    test needs every stage but no assembly's (mates, inspection, export): half the work."""
    import shutil

    root = tmp_path_factory.mktemp("parts-library")
    for category in (c for c in SMALL_LIBRARY if c != "assemblies"):
        shutil.copytree(small_library / category, root / category)
    return root


def free_port() -> int:
    """A TCP port nobody listens on now (loopback)."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture(scope="session")
def prefect_api(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """A real Prefect server on SQLite on a free loopback port; yields its environment."""
    from flows.server import server_env, start_server, stop_server

    home, port = tmp_path_factory.mktemp("prefect-home"), free_port()
    proc = start_server(home, port, timeout_s=180)
    yield server_env(home, port)
    from prefect.logging.handlers import APILogWorker

    APILogWorker.drain_all(timeout=5)  # the logs of flows run in this process, while it is up
    stop_server(proc)


# The threads of a test night's libraries: one per process (two test workers on two cores),
# set in every variable the CAD workers set, so that the stages' worker pools of no thread
# setting and of one thread share their workers (``cadio.sandbox``).
ONE_THREAD = {name: "1" for name in THREAD_VARIABLES}


# The inspection of the test nights: one view, no near ring, the design's route only. The
# search, the near ring and the planted defects are the tests' of cadio.inspect and of one
# night in test_flows; in every night they would double its time.
TEST_INSPECTION = {"views": 1, "near_m": 0.0, "defects": False, "search": False}


def _test_night(library: Path, workspace: Path, groups: dict[str, dict[str, object]]
                ) -> dict[str, dict[str, object]]:
    """A night's configuration with the small test settings, and ``groups`` on top."""
    config: dict[str, dict[str, object]] = {
        "library": {"path": str(library)}, "runtime": {"workspace": str(workspace)},
        "capture": {"views_per_scene": 1, "pairs_per_relation": 1},
        "inspection": TEST_INSPECTION, "thresholds": {"fail_on_threshold": False}}
    for name, values in groups.items():
        config.setdefault(name, {}).update(values)
    return config


@contextlib.contextmanager
def served_by(env: dict[str, str]) -> Iterator[None]:
    """Flows and ``mateqa`` commands of this process against the Prefect server of ``env``
    (Prefect's settings, which it read when it was imported, and the variable the commands
    read)."""
    from prefect.settings import PREFECT_API_URL, temporary_settings

    with pytest.MonkeyPatch.context() as patch, temporary_settings(
            {PREFECT_API_URL: env["PREFECT_API_URL"]}):
        patch.setenv("PREFECT_API_URL", env["PREFECT_API_URL"])
        yield


def run_night(library: Path, workspace: Path, env: dict[str, str],
              **groups: dict[str, object]) -> None:
    """``start_night``'s night run to its end in this process, which has imported what a night
    process spends 10-15 s importing, and whose stage workers' fork server runs already."""
    from flows.config import night_config
    from flows.nightly import nightly

    with served_by(env):
        nightly(night_config(_test_night(library, workspace, groups)))


def start_night(library: Path, workspace: Path, env: dict[str, str],
                **groups: dict[str, object]):  # type: ignore[no-untyped-def]
    """The nightly flow on ``library`` in a child process (its own session, so that it and its
    CAD workers can be killed together), with the small test settings and ``groups`` of the
    night's configuration on top (e.g. ``runtime={"dask_address": ...}``)."""
    import subprocess
    import sys

    config = _test_night(library, workspace, groups)
    code = ("from flows.config import night_config; from flows.nightly import nightly; "
            f"nightly(night_config({config!r}))")
    log = Path(workspace).with_name(f"{Path(workspace).name}.log")
    with log.open("ab") as out:  # a file, not a pipe: nobody reads while the night runs
        proc = subprocess.Popen([sys.executable, "-c", code], cwd=Path(__file__).parents[1],
                                env={**env, **ONE_THREAD}, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
    proc.log = log
    return proc


def finish_night(proc) -> None:  # type: ignore[no-untyped-def]
    """Wait for a night started by ``start_night``; its output when it failed."""
    assert proc.wait(900) == 0, proc.log.read_text()[-4000:]


@pytest.fixture(scope="session")
def local_night(small_library: Path, prefect_api: dict[str, str],
                tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder of an uninterrupted night on ``small_library`` (this machine's runner)."""
    workspace = tmp_path_factory.mktemp("local-night")
    run_night(small_library, workspace, prefect_api)
    return (workspace / "runs" / "latest").resolve()


# Test files that share a worker's session fixtures: those of the uninterrupted night (and its
# Prefect server) are one scheduling unit, so that the night is made once; those that need only
# the server another, so that the two run side by side (one unit of both left the other worker
# idle for minutes at the end of the run).
GROUPS = {"night": {"test_calibrate", "test_dask", "test_export", "test_resume"},
          "server": {"test_bad_inputs", "test_docker", "test_verdict", "test_workspace_claim"}}


# The heaviest scopes of the run (a test file, or a group of GROUPS), heaviest first: xdist
# hands scopes out in collection order, so these go first and the many small files fill in at
# the end; by number of tests (xdist's own order) a heavy file could start last and leave the
# other worker idle.
HEAVY_FIRST = ("night", "test_deployments", "server", "test_flows", "test_untrusted_names",
               "test_server", "test_assembly_variants", "test_mates", "test_samples",
               "test_integrate", "test_real_ingest", "test_relations_model")


def _scope(path: str) -> str:
    """The scheduling unit of a test file: its group in GROUPS, else the file."""
    stem = Path(path).stem
    return next((group for group, stems in GROUPS.items() if stem in stems), path)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Collect the heaviest scopes first (``HEAVY_FIRST``); the rest keep their order."""
    def rank(item: pytest.Item) -> int:
        path = item.nodeid.split("::", 1)[0]
        key = _scope(path)
        key = key if key in GROUPS else Path(path).stem
        return HEAVY_FIRST.index(key) if key in HEAVY_FIRST else len(HEAVY_FIRST)

    items.sort(key=rank)  # stable: a file's tests keep their order


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object:
    """pytest-xdist's scheduler by test file (a file's module fixtures are set up once), with
    the files of each group of ``GROUPS`` one unit (xdist's own ``loadgroup`` marks are not
    honoured under this pytest: it no longer lets a plugin rename a test's node id)."""
    from xdist.scheduler import LoadScopeScheduling

    class FileScheduling(LoadScopeScheduling):  # type: ignore[misc]
        def _split_scope(self, nodeid: str) -> str:
            return _scope(nodeid.split("::", 1)[0])

    return FileScheduling(config, log)
