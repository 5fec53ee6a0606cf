"""The training library and corpus: what ``mateqa train`` learns from, built as the night sees.

1. library: the sample library with parametric variants of its parts and assemblies
   (``cadio.samples``), plus the real parts of a shared STEP folder where given, ingested
   into the training workspace;
2. pair scenes of the single parts (``cadio.truth.scenes``), kept while their stamp holds;
3. the corpus (``models.training.corpus``): every distinct part alone, the pair scenes, every
   multi-part file as placed, rendered and cut into the night's inputs; split by source file
   and part (a shape held out anywhere is held out everywhere): the nightly's own sample
   library is never trained on, half of the shared real files are held out whole
   (``groups.csv`` of the corpus lists each file's split).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from cadio.cad.ingest import IngestConfig, discover, ingest_files, mark_duplicates
from cadio.catalog import read_catalog, to_frame, write_catalog
from cadio.samples.assembly_variants import FAMILIES, write_assembly_variants
from cadio.samples.library import SampleConfig, generate_library
from cadio.truth.scene_config import SceneConfig
from cadio.truth.scenes import (
    generate_scenes,
    read_scene_parts,
    read_scenes,
    scenes_stamp,
    write_scenes,
)
from cadio.workspace import Workspace
from models.training.corpus import (
    KINDS,
    CorpusConfig,
    build_corpus,
    plan_corpus,
    plan_splits,
)

log = logging.getLogger(__name__)

Progress = Callable[[str], None]


@dataclass(frozen=True)
class Corpus:
    """Where the training examples are and how many parts, shots and examples each holds."""

    dataset: str
    parts: int
    splits: dict[str, int]
    failed: int
    shots: dict[str, int] = field(default_factory=dict)
    examples: int = 0
    seconds: float = 0.0


def corpus_library(ws: Workspace) -> Path:
    """The training library: the sample library with its variants."""
    return ws.root / "library-train"


def corpus_fractions(library: Path, shared: Path | None) -> Callable[[str], tuple[float, float]]:
    """(val, test) fractions of each source file's draw: the nightly's own sample library is
    always held out; real files of ``shared`` are held out by half (whole files, so a held-out
    assembly's night is on parts no network saw); generated variants by a fifth."""
    originals, real = str(library), None if shared is None else str(Path(shared).resolve())

    def fractions(source: str) -> tuple[float, float]:
        if source.startswith(originals) and "/variants/" not in source:
            return 0.0, 1.0
        if real is not None and str(Path(source).resolve()).startswith(real):
            return 0.1, 0.5
        return 0.1, 0.2

    return fractions


@dataclass(frozen=True)
class CorpusPlan:
    """What the corpus is made of: the real files of ``shared`` (None: the generated library
    only), ``variants`` per category of the sample library, ``assemblies`` seeded assembly
    variants, the pair scenes (``pairs_per_relation``, and ``contact_pairs`` and
    ``clearance_pairs``: touching pairs and coaxial pairs apart, ``SceneConfig``), the
    ``kinds`` of shot rendered (the relation networks need no part alone), all drawn from
    ``seed``."""

    shared: Path | None = None
    variants: int = 100
    seed: int = 0
    pairs_per_relation: int = 150
    assemblies: int = 20 * len(FAMILIES)
    contact_pairs: int = 0
    clearance_pairs: int = 0
    kinds: tuple[str, ...] = KINDS

    def scenes(self) -> SceneConfig:
        return SceneConfig(seed=self.seed, pairs_per_relation=self.pairs_per_relation,
                           contact_pairs=self.contact_pairs, clearance_pairs=self.clearance_pairs)


def prepare_corpus(ws: Workspace, plan: CorpusPlan, ingest_cfg: IngestConfig,
                   corpus_cfg: CorpusConfig, progress: Progress | None = None) -> Corpus:
    """Library with variants of its parts and assemblies (+ shared parts), ingest, pair
    scenes, the corpus of shots (``models.training.corpus``). Reruns reuse every step; a stopped
    build resumes."""
    clock = time.perf_counter()
    library = corpus_library(ws)
    generate_library(library, SampleConfig(variants=plan.variants, variant_seed=plan.seed))
    write_assembly_variants(library / "assemblies" / "variants", plan.assemblies, plan.seed,
                            workers=ingest_cfg.limits.workers)
    found = discover(library) + (discover(plan.shared) if plan.shared is not None else [])
    rows = ingest_files(found, ws.root, ingest_cfg, read_catalog(ws.catalog))
    catalog = to_frame(mark_duplicates(rows))
    write_catalog(ws.catalog, catalog)
    fractions = corpus_fractions(library, plan.shared)
    out = dataset_dir(ws)
    out.mkdir(parents=True, exist_ok=True)
    scenes = _corpus_scenes(ws, catalog, fractions, plan.scenes(), out)
    shots_plan = plan_corpus(catalog, ws.mesh, scenes, fractions, plan.seed)
    groups = pd.DataFrame(sorted(shots_plan.group_split.items()), columns=["source", "split"])
    groups.to_csv(out / "groups.csv", index=False)
    shots = [s for s in shots_plan.shots if s.kind in plan.kinds]
    index = build_corpus(shots, out, corpus_cfg, ingest_cfg.limits, progress)
    ok = index[index["status"] == "ok"]
    per_split = ok.drop_duplicates("part_id")["split"].value_counts().to_dict()
    per_kind = pd.Series([s.kind for s in shots]).value_counts().to_dict()
    return Corpus(str(out), int(ok["part_id"].nunique()),
                  {str(k): int(v) for k, v in per_split.items()},
                  int((index["status"] == "failed").sum()),
                  {str(k): int(v) for k, v in per_kind.items()}, len(ok),
                  time.perf_counter() - clock)


def _corpus_scenes(ws: Workspace, catalog: pd.DataFrame,
                   fractions: Callable[[str], tuple[float, float]], cfg: SceneConfig,
                   out: Path) -> pd.DataFrame:
    """The pair scenes of the corpus's single parts (each part in its corpus split), kept in
    the corpus folder and reused while their stamp holds (the same config and placement rules;
    a table drawn by other rules is drawn anew, and its shots with it)."""
    path = out / "scenes.parquet"
    if path.exists():
        kept = read_scenes(path)
        if kept.attrs["config"] == scenes_stamp(cfg):
            return kept
        log.info("%s: drawn by other rules or another config; drawing the scenes anew", path)
    _, part_split = plan_splits(catalog, fractions, cfg.seed)
    parts = [p for p in read_scene_parts(catalog, ws.root) if p.part_id in part_split]
    scenes = generate_scenes(parts, cfg, part_split)
    write_scenes(path, scenes)
    return scenes


def dataset_dir(ws: Workspace) -> Path:
    return ws.root / "datasets" / "corpus"


def corpus_note(corpus: Corpus) -> str:
    """One sentence on the corpus: its shots by kind, examples, parts and build time."""
    kinds = ", ".join(f"{n} {k}" for k, n in sorted(corpus.shots.items()))
    rate = sum(corpus.shots.values()) / corpus.seconds if corpus.seconds else float("nan")
    return (f"Corpus: {sum(corpus.shots.values())} shots ({kinds}), {corpus.examples} examples "
            f"of {corpus.parts} parts (per split {corpus.splits}), built in "
            f"{corpus.seconds / 60:.0f} min on 2 cores ({rate:.2f} shots/s).")


