"""Seeded parametric variants of the sample assembly families, written as STEP assemblies.

Five fixed assemblies are too few to train on parts as they are placed in assemblies. Each
family here (bearings in a housing, open ball bearings with their balls apart, bolted lap
joints, casters, gear pairs, pillow blocks, sleeve, jaw and flange couplings, pulleys on studs,
bars in guide grooves, carriages on rails, keyed hubs)
draws its sizes, counts and options from a
seeded generator and places named, coloured parts as a real assembly has them: faces in contact
without interference, shafts coaxial with their bores, parts resting on one another. A variant
also says which face mates its layout is built to have (``Mate``), so the ground truth can be
held against the design. Variants are never the library's own five (other parameters).

Variant k of a family depends only on (seed, family, k), whatever the count or the families
asked for; ``write_assembly_variants`` writes one STEP file per variant the way the sample
library writes its assemblies (one labelled, coloured solid per part: product names and
colours), byte for byte the same for the same seed, and skips files already up to date. Layout
under ``out_dir``::

    <family>-v<k>.step          one assembly per file
    ASSEMBLY_VARIANTS.json      stamp and one entry per file (see ``VariantEntry``)
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import build123d as bd
import numpy as np
import pandas as pd

from cadio.cad.step import write_step
from cadio.errors import InputFileError
from cadio.samples.assembly_kit import CONCENTRIC, Design, Mate
from cadio.samples.joint_assemblies import (
    draw_bolted_joint,
    draw_caster,
    draw_flange_coupling,
    draw_jaw_coupling,
    draw_sleeve_coupling,
)
from cadio.samples.library import SampleConfig, _sha256, package_versions
from cadio.samples.parts import dress_solid
from cadio.samples.shaft_assemblies import (
    draw_ball_bearing,
    draw_bearing_shaft,
    draw_gear_pair,
    draw_pillow_blocks,
    draw_pulley_drive,
)
from cadio.samples.slide_assemblies import (
    draw_keyed_hub,
    draw_rail_carriage,
    draw_segmented_ring,
    draw_slide_guide,
)
from cadio.sandbox import Job, Limits, run_isolated
from cadio.workspace import write_json

logger = logging.getLogger(__name__)

VARIANTS_INDEX = "ASSEMBLY_VARIANTS.json"
# Bump whenever a family's layout, parameters, names or colours change: it invalidates written
# variants.
ASSEMBLY_VARIANTS_VERSION = 1

FAMILIES: dict[str, Callable[[np.random.Generator], Design]] = {
    "bearing-shaft": draw_bearing_shaft,
    "bolted-joint": draw_bolted_joint,
    "caster": draw_caster,
    "gear-pair": draw_gear_pair,
    "pillow-block": draw_pillow_blocks,
    "sleeve-coupling": draw_sleeve_coupling,
    "jaw-coupling": draw_jaw_coupling,
    "flange-coupling": draw_flange_coupling,
    "pulley-drive": draw_pulley_drive,
    "ball-bearing": draw_ball_bearing,
    "slide-guide": draw_slide_guide,
    "rail-carriage": draw_rail_carriage,
    "keyed-hub": draw_keyed_hub,
    "segmented-ring": draw_segmented_ring,
}


@dataclass(frozen=True)
class AssemblyVariant:
    """One drawn assembly (``<family>-v<index>``); nothing is built until ``build`` is called."""

    family: str
    index: int
    name: str
    design: Design

    @property
    def description(self) -> str:
        """The drawn parameters."""
        return self.design.description

    @property
    def parts(self) -> tuple[str, ...]:
        """Each part's label (its STEP product name), in file order."""
        return tuple(p.label for p in self.design.parts)

    @property
    def categories(self) -> tuple[str, ...]:
        """Each part's paper category ("" for plates and frames), in file order."""
        return tuple(p.category for p in self.design.parts)

    @property
    def mates(self) -> tuple[Mate, ...]:
        """The face mates the layout is built to have."""
        return self.design.mates

    def build(self) -> list[bd.Solid]:
        """The parts, each one valid solid, labelled and coloured, placed in the assembly.

        Raises:
            GeometryError: a part did not build into one valid solid.
        """
        return _own_colours([dress_solid(p.build(), p.label, p.colour)
                             for p in self.design.parts])

    def compound(self) -> bd.Compound:
        """The assembly as ``write_step`` takes it: one child per part."""
        return bd.Compound(children=self.build(), label=self.name)


def _own_colours(solids: list[bd.Solid]) -> list[bd.Solid]:
    """The solids with each repeat of a colour moved by a step of 1/255 (alternately up and
    down): OCCT writes one colour entity for parts of equal colour, shared between their style
    blocks, and ``write_step`` can only put style blocks in a canonical order (reproducible
    bytes) when no block refers to another's entities."""
    seen: dict[tuple[float, ...], int] = {}
    for solid in solids:
        rgba = tuple(solid.color) if solid.color is not None else (0.5, 0.5, 0.5, 1.0)
        k = seen.get(rgba, 0)
        seen[rgba] = k + 1
        if k:
            step = (k + 1) // 2 * (1 if k % 2 else -1) / 255
            solid.color = bd.Color(*[min(1.0, max(0.0, c + step)) for c in rgba[:3]])
    return solids


def draw_assembly_variant(family: str, index: int, seed: int = 0) -> AssemblyVariant:
    """Variant ``index`` of ``family``; it depends only on (seed, family, index).

    Raises:
        ValueError: ``family`` is not one of ``FAMILIES``.
    """
    if family not in FAMILIES:
        raise ValueError(f"unknown assembly family {family!r}; known: {', '.join(FAMILIES)}")
    rng = np.random.default_rng([seed, list(FAMILIES).index(family), index])
    return AssemblyVariant(family, index, f"{family}-v{index:04d}", FAMILIES[family](rng))


def draw_assembly_variants(count: int, seed: int = 0,
                           families: Sequence[str] | None = None) -> list[AssemblyVariant]:
    """``count`` variants, the families taken in turn (variant i is number i // F of family
    i % F), so that a larger count only adds variants.

    Args:
        count: variants in all (0 for none).
        seed: the generator's seed.
        families: names from ``FAMILIES`` (default: all, in ``FAMILIES`` order).

    Returns:
        Variants in draw order; nothing is built yet.

    Raises:
        ValueError: a family is unknown or the list is empty.
    """
    names = list(FAMILIES) if families is None else list(families)
    if not names:
        raise ValueError("no assembly family asked for")
    return [draw_assembly_variant(names[i % len(names)], i // len(names), seed)
            for i in range(count)]


# --------------------------------------------------------------------------- checks


def missing_mates(promised: Iterable[Mate], face_mates: pd.DataFrame) -> list[Mate]:
    """The promised mates that a face-level mates table does not have.

    Args:
        promised: a variant's ``mates``.
        face_mates: rows of a mates table (``cadio.truth.mates``) with at least the columns
            name_a, name_b, relation and fit; part names are the variant's labels.

    Returns:
        Each promised mate with no row of its relation (and fit, for a concentric one)
        between its two parts, in either order.
    """
    found = {(frozenset((str(a), str(b))), str(rel), fit if rel == CONCENTRIC else None)
             for a, b, rel, fit in face_mates[["name_a", "name_b", "relation", "fit"]]
             .itertuples(index=False)}
    return [m for m in promised
            if (frozenset((m.a, m.b)), m.relation, m.fit if m.relation == CONCENTRIC else None)
            not in found]


def overlaps(solids: Sequence[bd.Solid], tol_mm3: float = 1e-3) -> list[tuple[str, str, float]]:
    """Pairs of parts that share more than ``tol_mm3`` of volume: (label, label, mm^3).

    Parts whose boxes or exact distance keep them apart are not intersected (a gear pair's
    Boolean common alone takes seconds).
    """
    out = []
    boxes = [s.bounding_box() for s in solids]
    for i, a in enumerate(solids):
        for j in range(i + 1, len(solids)):
            b = solids[j]
            if not boxes[i].overlaps(boxes[j]) or a.distance_to(b) > 0.0:
                continue
            common = a.intersect(b)
            volume = 0.0 if common is None else sum(s.volume for s in common.solids())
            if volume > tol_mm3:
                out.append((a.label, b.label, volume))
    return out


# --------------------------------------------------------------------------- writing


@dataclass(frozen=True)
class VariantEntry:
    """One file listed in ASSEMBLY_VARIANTS.json; ``path`` is relative to the folder.

    mates: the promised face mates as (part a, part b, relation, fit or None).
    """

    path: str
    family: str
    index: int
    name: str
    description: str
    parts: tuple[str, ...]
    categories: tuple[str, ...]
    mates: tuple[tuple[str, str, str, str | None], ...]
    sha256: str


@dataclass(frozen=True)
class _VariantJob:
    """What a worker needs to draw, build and write one variant (all picklable)."""

    family: str
    index: int
    seed: int
    out_dir: str
    timestamp: str


def write_variant(job: _VariantJob) -> VariantEntry:
    """Draw, build and write one variant (the job of a worker process).

    Raises:
        GeometryError: the draw did not build into valid solids.
    """
    v = draw_assembly_variant(job.family, job.index, job.seed)
    rel = f"{v.name}.step"
    path = Path(job.out_dir) / rel
    write_step(v.compound(), path, job.timestamp)
    return VariantEntry(path=rel, family=v.family, index=v.index, name=v.name,
                        description=v.description, parts=v.parts, categories=v.categories,
                        mates=tuple((m.a, m.b, m.relation, m.fit) for m in v.mates),
                        sha256=_sha256(path))


def _stamp(seed: int, timestamp: str) -> dict[str, Any]:
    """What every file depends on: a change to any of these rewrites the folder."""
    return {"version": ASSEMBLY_VARIANTS_VERSION, "seed": seed, "step_timestamp": timestamp,
            "packages": package_versions()}


def _reusable(out_dir: Path, stamp: dict[str, Any]) -> dict[str, VariantEntry]:
    """Entries of an existing index with this stamp whose files still have their hash."""
    try:
        data = json.loads((out_dir / VARIANTS_INDEX).read_text())
        if data["stamp"] != stamp:
            return {}
        entries = [_entry(e) for e in data["files"]]
    except (OSError, ValueError, KeyError, TypeError):
        return {}
    return {e.name: e for e in entries
            if (out_dir / e.path).is_file() and _sha256(out_dir / e.path) == e.sha256}


def _entry(data: dict[str, Any]) -> VariantEntry:
    mates = tuple((a, b, rel, fit) for a, b, rel, fit in data["mates"])
    return VariantEntry(**{**data, "parts": tuple(data["parts"]),
                           "categories": tuple(data["categories"]), "mates": mates})


def write_assembly_variants(out_dir: Path, count: int, seed: int = 0, *,
                            families: Sequence[str] | None = None, workers: int = 2,
                            timestamp: str = SampleConfig().step_timestamp
                            ) -> list[VariantEntry]:
    """Write ``count`` assembly variants (see ``draw_assembly_variants``) under ``out_dir``.

    A variant whose file the index lists under the same stamp (version, seed, time stamp,
    package versions) and description, with its recorded hash, is left alone; the others are
    built and written by ``workers`` processes (one builds in this process). A variant that
    fails to build is left out and logged. Files of an earlier index that are no longer asked
    for are removed; the index is written last.

    Args:
        out_dir: the folder (created if missing).
        count, seed, families: as ``draw_assembly_variants``.
        workers: processes building variants at once.
        timestamp: the STEP header's time stamp.

    Returns:
        The entries of the files written or kept, in draw order.

    Raises:
        ValueError: a family is unknown.
    """
    start = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    variants = draw_assembly_variants(count, seed, families)
    stamp = _stamp(seed, timestamp)
    previous = _previous_paths(out_dir)
    kept = {name: e for name, e in _reusable(out_dir, stamp).items()}
    todo = [_VariantJob(v.family, v.index, seed, str(out_dir), timestamp) for v in variants
            if not (v.name in kept and kept[v.name].description == v.description)]
    written = {e.name: e for e in _run(todo, workers)}
    entries = [e for v in variants
               if (e := written.get(v.name) or kept.get(v.name)) is not None]
    _write_index(out_dir / VARIANTS_INDEX, {"stamp": stamp,
                                            "files": [asdict(e) for e in entries]})
    for stale in sorted(previous - {e.path for e in entries}):
        if stale.endswith(".step") and "/" not in stale:  # never leave out_dir
            (out_dir / stale).unlink(missing_ok=True)
    logger.info("assembly variants in %s: %d written, %d kept, %d left out, %.1f s", out_dir,
                len(written), len(entries) - len(written), len(variants) - len(entries),
                time.perf_counter() - start)
    return entries


def _write_index(path: Path, data: dict[str, Any]) -> None:
    """``write_json``, unless the file already holds exactly that (its mtime stays)."""
    try:
        if path.read_text() == json.dumps(data, indent=1, sort_keys=True):
            return
    except OSError:
        pass
    write_json(path, data)


def _previous_paths(out_dir: Path) -> set[str]:
    try:
        return {str(e["path"]) for e in json.loads((out_dir / VARIANTS_INDEX).read_text())
                ["files"]}
    except (OSError, ValueError, KeyError, TypeError):
        return set()


def _run(jobs: list[_VariantJob], workers: int) -> list[VariantEntry]:
    """Build and write each job, in this process or in ``workers`` isolated ones."""
    if workers <= 1 or len(jobs) <= 1:
        return [e for e in map(_try_write, jobs) if e is not None]
    limits = Limits(seconds=600.0, workers=workers)
    out = []
    for outcome in run_isolated(write_variant, [Job(f"{j.family}-v{j.index:04d}", j)
                                                for j in jobs], limits):
        if outcome.result is not None:
            out.append(outcome.result)
        else:
            logger.warning("assembly variant %s left out: %s", outcome.job.key,
                           outcome.error.reason if outcome.error else "no result")
    return out


def _try_write(job: _VariantJob) -> VariantEntry | None:
    try:
        return write_variant(job)
    except Exception as exc:  # the kernel's errors share no base class but Exception
        logger.warning("assembly variant %s-v%04d left out: %s", job.family, job.index, exc)
        return None


def read_assembly_variants(out_dir: Path) -> list[VariantEntry]:
    """The entries of ``out_dir/ASSEMBLY_VARIANTS.json``, in draw order.

    Raises:
        InputFileError: the index is missing or not one written by ``write_assembly_variants``.
    """
    index = out_dir / VARIANTS_INDEX
    try:
        return [_entry(e) for e in json.loads(index.read_text())["files"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputFileError(index, f"not an assembly variants index ({exc})") from exc
