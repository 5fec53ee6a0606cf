"""The built-in sample part library: STEP files the product generates for itself.

mateqa cannot ship vendors' STEP files, so a first run builds a small library in the four
paper categories plus a few assemblies with known mates, from build123d and bd_warehouse
geometry (millimetres, Z up). Layout under ``out_dir``::

    <category>/<name>.step     one solid per file (a bearing is one fused solid)
    assemblies/<name>.step     one named, coloured solid per part, placed in contact
    LIBRARY.json               version stamp and one entry per file (see ``LibraryEntry``)

Files are byte-identical across runs and machines (fixed STEP header time stamp, no
randomness), so content hashes downstream stay stable; a rerun whose stamp and hashes match
returns at once. Every write is atomic. The geometry lives in ``cadio.samples.parts`` and
``cadio.samples.assemblies``; the deterministic STEP writer in ``cadio.cad.step``.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import build123d as bd

from cadio.cad.step import write_step
from cadio.errors import InputFileError
from cadio.records import Category
from cadio.samples.assemblies import assembly_builders
from cadio.samples.parts import (
    Builder,
    brake_builders,
    caster_builders,
    dress_solid,
    fastener_builders,
    motion_builders,
)
from cadio.samples.variants import draw_variants
from cadio.workspace import write_json

logger = logging.getLogger(__name__)

ASSEMBLIES = "assemblies"
LIBRARY_INDEX = "LIBRARY.json"
# Bump whenever any geometry, name or colour changes: it invalidates generated libraries.
LIBRARY_VERSION = 2


@dataclass(frozen=True)
class SampleConfig:
    """Knobs of the sample library."""

    # STEP headers carry a time stamp; a constant one keeps the files' bytes reproducible.
    step_timestamp: str = "2000-01-01T00:00:00"
    # Involute gears are the slowest parts (~0.3-1 s each); off leaves 14 motion parts.
    gears: bool = True
    # Parametric variants per paper category (``cadio.samples.variants``), for training the
    # learned stages; the nightly's built-in library has none.
    variants: int = 0
    variant_seed: int = 0


@dataclass(frozen=True)
class SampleSpec:
    """One file of the library: where it goes and how to build its shape."""

    category: str  # a Category value, or ASSEMBLIES
    name: str
    description: str
    build: Callable[[], bd.Shape[Any]]
    # A variant whose draw does not build into one valid solid is left out (logged), not fatal.
    optional: bool = False


@dataclass(frozen=True)
class LibraryEntry:
    """One file listed in LIBRARY.json. ``path`` is relative to the library folder (posix)."""

    path: str
    category: str
    name: str
    description: str
    n_solids: int
    parts: tuple[str, ...]  # solid labels in file order
    sha256: str


# --------------------------------------------------------------------------- the library


def _single(build: Builder, name: str, colour: str) -> Builder:
    return lambda: dress_solid(build(), name, colour)


def _compound(build: Callable[[], list[bd.Solid]], name: str) -> Callable[[], bd.Shape[Any]]:
    return lambda: bd.Compound(children=build(), label=name)


def sample_specs(cfg: SampleConfig | None = None) -> list[SampleSpec]:
    """Every file of the library, in a fixed order; nothing is built until ``spec.build()``.

    Args:
        cfg: library knobs; defaults to ``SampleConfig()``.

    Returns:
        Specs of the single parts of the four categories, then of the assemblies.
    """
    cfg = cfg or SampleConfig()
    groups = [(Category.FASTENERS, fastener_builders(), "zinc"),
              (Category.MOTION, motion_builders(cfg.gears), "steel"),
              (Category.BRAKES, brake_builders(), "iron"),
              (Category.CASTERS, caster_builders(), "red")]
    specs = [SampleSpec(cat.value, name, desc, _single(build, name, colour))
             for cat, items, colour in groups for name, desc, build in items]
    specs += [SampleSpec(ASSEMBLIES, name, desc, _compound(build, name))
              for name, desc, build in assembly_builders()]
    specs += [SampleSpec(v.category, f"variants/{v.name}", v.description, v.build, optional=True)
              for v in draw_variants(cfg.variants, cfg.variant_seed)]
    return specs


def package_versions() -> dict[str, str]:
    """Versions of the packages the generated geometry depends on."""
    versions = {}
    for dist in ("build123d", "bd_warehouse", "cadquery-ocp"):
        try:
            versions[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            versions[dist] = "unknown"
    return versions


def _stamp(cfg: SampleConfig) -> dict[str, Any]:
    """What the files depend on: a change to any of these regenerates the library."""
    return {"version": LIBRARY_VERSION, "config": asdict(cfg), "packages": package_versions()}


def _labels(shape: bd.Shape[Any]) -> tuple[str, ...]:
    if isinstance(shape, bd.Compound) and shape.children:
        return tuple(child.label for child in shape.children)
    return (shape.label,)


def _write_sample(out_dir: Path, spec: SampleSpec, cfg: SampleConfig) -> LibraryEntry | None:
    """Build one spec and write its STEP file unless identical bytes are already there.

    Returns None for an optional spec that does not build (a variant drawn out of range).
    """
    try:
        shape = spec.build()
    except Exception as exc:  # the kernel's errors share no base class but Exception
        if not spec.optional:
            raise
        logger.warning("variant %s (%s) left out: %s", spec.name, spec.description, exc)
        return None
    rel = f"{spec.category}/{spec.name}.step"
    write_step(shape, out_dir / rel, cfg.step_timestamp)
    return LibraryEntry(path=rel, category=spec.category, name=spec.name,
                        description=spec.description, n_solids=len(shape.solids()),
                        parts=_labels(shape), sha256=_sha256(out_dir / rel))


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _previous(out_dir: Path) -> tuple[dict[str, Any], dict[str, str]]:
    """Stamp and {relative path: sha256} of an existing index; empty when there is none."""
    try:
        data = json.loads((out_dir / LIBRARY_INDEX).read_text())
        return dict(data["stamp"]), {e["path"]: e["sha256"] for e in data["files"]}
    except (OSError, ValueError, KeyError, TypeError):
        return {}, {}


def _up_to_date(out_dir: Path, stamp: dict[str, Any]) -> list[Path] | None:
    """The library's paths if its index has this stamp and every file its recorded hash."""
    old_stamp, hashes = _previous(out_dir)
    if old_stamp != stamp or not hashes:
        return None
    paths = {rel: out_dir / rel for rel in hashes}
    if not all(p.is_file() and _sha256(p) == hashes[rel] for rel, p in paths.items()):
        return None
    return sorted(paths.values())


def generate_library(out_dir: Path, cfg: SampleConfig | None = None) -> list[Path]:
    """Write the sample library under ``out_dir`` (see the module docstring for the layout).

    A library whose LIBRARY.json carries the same stamp (library version, config, package
    versions) and whose files match their recorded hashes is left alone; otherwise every
    shape is rebuilt, only files whose bytes differ are rewritten, and files the previous
    index listed that are no longer part of the library are removed. LIBRARY.json is
    written last, so an interrupted run is redone on the next call.

    Args:
        out_dir: the library folder (for a workspace, ``Workspace.library``).
        cfg: library knobs; defaults to ``SampleConfig()``.

    Returns:
        Paths of all STEP files, sorted.

    Raises:
        GeometryError: a sample did not build into valid solids (a bug or a changed kernel).
    """
    cfg = cfg or SampleConfig()
    stamp = _stamp(cfg)
    current = _up_to_date(out_dir, stamp)
    if current is not None:
        logger.debug("sample library in %s is up to date", out_dir)
        return current
    start = time.perf_counter()
    _, previous = _previous(out_dir)
    written = [_write_sample(out_dir, spec, cfg) for spec in sample_specs(cfg)]
    entries = [e for e in written if e is not None]
    write_json(out_dir / LIBRARY_INDEX, {"stamp": stamp, "files": [asdict(e) for e in entries]})
    for stale in sorted(set(previous) - {e.path for e in entries}):
        if stale.endswith(".step") and ".." not in Path(stale).parts:  # never leave out_dir
            (out_dir / stale).unlink(missing_ok=True)
    logger.info("generated %d sample files in %s in %.1f s", len(entries), out_dir,
                time.perf_counter() - start)
    return sorted(out_dir / e.path for e in entries)


def read_library(out_dir: Path) -> list[LibraryEntry]:
    """The entries of ``out_dir/LIBRARY.json``, in library order.

    Args:
        out_dir: a folder written by ``generate_library``.

    Returns:
        One entry per STEP file: the single parts of the four categories, then assemblies.

    Raises:
        InputFileError: the index is missing or not one written by ``generate_library``.
    """
    index = out_dir / LIBRARY_INDEX
    try:
        files = json.loads(index.read_text())["files"]
        return [LibraryEntry(**{**e, "parts": tuple(e["parts"])}) for e in files]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputFileError(index, f"not a sample library index ({exc})") from exc
