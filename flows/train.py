"""Training the learned stages: the corpus, the networks, their held-out scores, the model card.

``mateqa train completion`` runs these steps in the process (progress bars, no server); the
``train`` flow runs the same steps as Prefect tasks. Each step is one call into the packages:

1. library: the sample library with parametric variants (``cadio.samples``), plus the real
   parts of a shared STEP folder where given, ingested into the training workspace;
2. corpus: what the nightly's cameras see, cut into its inputs (``cadio.capture.corpus``):
   every distinct part alone, pair scenes of the single parts, every multi-part file as
   placed; split by source file and part (a shape held out anywhere is held out everywhere):
   the nightly's own sample library is never trained on, half of the shared real files are
   held out whole (``groups.csv`` of the corpus lists each file's split);
3. training of each learned method and protocol (``models``), checkpoints self-describing;
4. evaluation on the held-out parts beside the baselines (``models.evaluate``), written as the
   run's completion report and the model card;
5. the relation networks on the same corpus (``flows.train_relations``): labels, the pair
   dataset completed by the checkpoints of step 3, ``ltn`` and ``mlp`` on each input, their
   held-out report and card.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pandas as pd
from prefect import flow, get_run_logger, task

from cadio.cad.ingest import IngestConfig, discover, ingest_files, mark_duplicates
from cadio.capture.corpus import (
    KINDS,
    CorpusConfig,
    build_corpus,
    plan_corpus,
    plan_splits,
    read_index,
)
from cadio.capture.examples import PROTOCOLS
from cadio.capture.pairs import INPUTS
from cadio.catalog import read_catalog, to_frame, write_catalog
from cadio.samples.assembly_variants import FAMILIES, write_assembly_variants
from cadio.samples.library import SampleConfig, generate_library
from cadio.sandbox import Limits
from cadio.truth.scenes import (
    SceneConfig,
    generate_scenes,
    read_scene_parts,
    read_scenes,
    scenes_stamp,
    write_scenes,
)
from cadio.workspace import Workspace
from models.evaluate import LEARNED

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


def prepare_corpus(ws: Workspace, shared: Path | None, variants: int, seed: int,
                   ingest_cfg: IngestConfig, corpus_cfg: CorpusConfig,
                   progress: Progress | None = None, pairs_per_relation: int = 150,
                   assemblies: int = 20 * len(FAMILIES), contact_pairs: int = 0,
                   clearance_pairs: int = 0,
                   kinds: tuple[str, ...] = KINDS) -> Corpus:
    """Library with variants of its parts and assemblies (+ shared parts), ingest, pair
    scenes, the corpus of shots (``cadio.capture.corpus``). Reruns reuse every step; a stopped
    build resumes. ``contact_pairs``, ``clearance_pairs``: touching pairs and coaxial pairs
    apart among the pair scenes (``SceneConfig``); ``kinds``: the kinds of shot rendered (the
    relation networks need no part alone)."""
    clock = time.perf_counter()
    library = corpus_library(ws)
    generate_library(library, SampleConfig(variants=variants, variant_seed=seed))
    write_assembly_variants(library / "assemblies" / "variants", assemblies, seed,
                            workers=ingest_cfg.limits.workers)
    found = discover(library) + (discover(shared) if shared is not None else [])
    rows = ingest_files(found, ws.root, ingest_cfg, read_catalog(ws.catalog))
    catalog = to_frame(mark_duplicates(rows))
    write_catalog(ws.catalog, catalog)
    fractions = corpus_fractions(library, shared)
    out = dataset_dir(ws)
    out.mkdir(parents=True, exist_ok=True)
    scenes = _corpus_scenes(ws, catalog, fractions, seed, pairs_per_relation, out, contact_pairs,
                            clearance_pairs)
    plan = plan_corpus(catalog, ws.mesh, scenes, fractions, seed)
    groups = pd.DataFrame(sorted(plan.group_split.items()), columns=["source", "split"])
    groups.to_csv(out / "groups.csv", index=False)
    shots = [s for s in plan.shots if s.kind in kinds]
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
                   fractions: Callable[[str], tuple[float, float]], seed: int,
                   pairs_per_relation: int, out: Path, contact_pairs: int = 0,
                   clearance_pairs: int = 0) -> pd.DataFrame:
    """The pair scenes of the corpus's single parts (each part in its corpus split), kept in
    the corpus folder and reused while their stamp holds (the same config and placement rules;
    a table drawn by other rules is drawn anew, and its shots with it)."""
    path = out / "scenes.parquet"
    cfg = SceneConfig(seed=seed, pairs_per_relation=pairs_per_relation,
                      contact_pairs=contact_pairs, clearance_pairs=clearance_pairs)
    if path.exists():
        kept = read_scenes(path)
        if kept.attrs["config"] == scenes_stamp(cfg):
            return kept
        log.info("%s: drawn by other rules or another config; drawing the scenes anew", path)
    _, part_split = plan_splits(catalog, fractions, seed)
    parts = [p for p in read_scene_parts(catalog, ws.root) if p.part_id in part_split]
    scenes = generate_scenes(parts, cfg, part_split)
    write_scenes(path, scenes)
    return scenes


def dataset_dir(ws: Workspace) -> Path:
    return ws.root / "datasets" / "corpus"


# ---------------------------------------------------------------- training and evaluation


@dataclass(frozen=True)
class Trained:
    """One trained checkpoint: where it went, its method and protocol, its best epoch."""

    path: str
    method: str
    protocol: str
    step: int
    val_iou: float
    seconds: float


def split_rows(ws: Workspace, protocol: str, split: str) -> pd.DataFrame:
    """The index rows of one protocol and split of the training dataset."""
    index = read_index(dataset_dir(ws) / "index.parquet")
    return index[(index["status"] == "ok") & (index["protocol"] == protocol)
                 & (index["split"] == split)]


def _files(ws: Workspace, rows: pd.DataFrame) -> list[Path]:
    return [dataset_dir(ws) / f for f in rows["file"]]


# Learning rates of the CPU default: the paper's Adam 1e-4 (generator) / 5e-5 (critic) suit
# long GPU runs; in a 2,000-step CPU budget they leave the models untrained (ae: validation
# IoU 0.20 after 200 steps at 1e-4, 0.51 at 1e-3), and a critic at half the generator's rate
# (5e-4) made gan_lstm's IoU fall back; 1e-4 kept it learning. The paper's rates remain a config.
CPU_RATES = {"lr": 1e-3, "lr_d": 1e-4}


def train_model(ws: Workspace, method: str, protocol: str, steps: int, out_dir: Path,
                on_step: Callable[[int, int, dict[str, float]], None] | None = None,
                rates: dict[str, float] | None = None, **overrides: Any) -> Trained:
    """Train one method on one protocol's training split; the best checkpoint by validation
    IoU goes to ``out_dir/completion-<method>-<protocol>.pt``, a resumable one beside the
    dataset (a rerun resumes it). ``rates``: learning rates (default ``CPU_RATES``; ``lr_d``
    only applies to methods with a critic)."""
    from models.checkpoint import save_checkpoint
    from models.data import CompletionDataset
    from models.train import config_for, train_completion

    rows = split_rows(ws, protocol, "train")
    train, val = _files(ws, rows), _files(ws, split_rows(ws, protocol, "val"))
    parts = sorted(set(rows["part_id"]))
    chosen = dict(CPU_RATES if rates is None else rates)
    if method != "gan_lstm":
        chosen.pop("lr_d", None)
    cfg = config_for(method, **{**chosen, **overrides})
    snapshot = ws.root / "models" / f"completion-{method}-{protocol}.resume.pt"
    clock = time.perf_counter()

    def progress(event: Any) -> None:
        if on_step is not None:
            on_step(event.step, event.steps, event.losses)
        if event.snapshot is not None:
            save_checkpoint(event.snapshot, snapshot)

    result = train_completion(
        cfg, CompletionDataset(paths=train), CompletionDataset(paths=val) if val else None,
        steps=steps, progress=progress, resume=snapshot if snapshot.exists() else None,
        data_info={"protocol": protocol, "train_parts": parts, "train_examples": len(train),
                   "val_examples": len(val), "dataset": str(dataset_dir(ws).relative_to(ws.root))})
    path = save_checkpoint(result.checkpoint, out_dir / f"completion-{method}-{protocol}.pt")
    best = result.checkpoint["metrics"]
    return Trained(str(path), method, protocol, int(result.checkpoint["step"]),
                   float(best.get("val_iou", float("nan"))), time.perf_counter() - clock)


def evaluate_models(ws: Workspace, models_dir: Path, run_dir: Path,
                    progress: Progress | None = None, per_group: int | None = None,
                    seed: int = 0) -> pd.DataFrame:
    """Every held-out example of the training dataset (or, with ``per_group``, a seeded draw of
    at most that many per kind of shot, category and number of views), completed by every
    method and scored; the completion report and the registration table are written into
    ``run_dir``."""
    from models.evaluate import load_models, score_files
    from reports.completion import parts_frame, write_completion

    index = read_index(dataset_dir(ws) / "index.parquet")
    test = index[(index["status"] == "ok") & (index["split"] == "test")]
    # one example per part, kind of shot, protocol and number of views (a part sits in many
    # shots: the report scores it once per context, as the nightly does)
    test = test.sample(frac=1.0, random_state=seed).drop_duplicates(
        ["part_id", "kind", "protocol", "n_views"])
    if per_group is not None:
        test = test.groupby(["kind", "category", "n_views"]).head(per_group)
    category = dict(zip(test["part_id"], test["category"], strict=False))
    models = load_models(models_dir)
    scores = score_files([dataset_dir(ws) / f for f in test["file"]], models,
                         lambda pid: "test", lambda pid: category.get(pid, "unknown"), progress)
    parts = parts_frame(scores.parts)
    write_completion(run_dir, parts)
    pd.DataFrame(scores.registration).to_csv(run_dir / "completion_registration.csv",
                                             index=False)
    return parts


def dataset_table(ws: Workspace) -> pd.DataFrame:
    """Parts and examples per split and category of the training dataset."""
    index = read_index(dataset_dir(ws) / "index.parquet")
    ok = index[index["status"] == "ok"]
    table = ok.groupby(["split", "category"]).agg(parts=("part_id", "nunique"),
                                                  examples=("file", "count")).reset_index()
    return table.sort_values(["split", "category"]).reset_index(drop=True)


def origin_of(ws: Workspace) -> dict[str, str]:
    """Part id -> where the part comes from: a generated variant, the sample library (which
    the nightly runs on, never trained on) or a real STEP file of the shared folder."""
    catalog = read_catalog(ws.catalog)
    library = str(corpus_library(ws))

    def origin(source: str) -> str:
        if not source.startswith(library):
            return "real STEP parts"
        return "generated variants" if "/variants/" in source else "sample library"

    return {str(p): origin(str(s)) for p, s in zip(catalog["part_id"], catalog["source"],
                                                   strict=True)}


def origin_table(ws: Workspace, run_dir: Path) -> pd.DataFrame:
    """Held-out single-view IoU by origin of the parts, method and protocol: whether the
    checkpoints generalise to real parts they never saw."""
    from reports.completion import read_completion_parts

    parts = read_completion_parts(run_dir)
    single = parts[(parts["split"] == "test") & (parts["n_views"] == 1)].copy()
    single["origin"] = single["part_id"].map(origin_of(ws)).fillna("unknown")
    per_part = single.groupby(["origin", "protocol", "method", "part_id"])["iou"].mean()
    table = per_part.groupby(["origin", "protocol", "method"]).agg(["count", "mean"])
    table = table.rename(columns={"count": "n_parts", "mean": "iou"}).reset_index()
    table["iou"] = (100 * table["iou"]).round(2)
    return table.pivot(index=["origin", "protocol"], columns="method",
                       values="iou").reset_index()


def corpus_note(corpus: Corpus) -> str:
    """One sentence on the corpus: its shots by kind, examples, parts and build time."""
    kinds = ", ".join(f"{n} {k}" for k, n in sorted(corpus.shots.items()))
    rate = sum(corpus.shots.values()) / corpus.seconds if corpus.seconds else float("nan")
    return (f"Corpus: {sum(corpus.shots.values())} shots ({kinds}), {corpus.examples} examples "
            f"of {corpus.parts} parts (per split {corpus.splits}), built in "
            f"{corpus.seconds / 60:.0f} min on 2 cores ({rate:.2f} shots/s).")


def write_model_card(ws: Workspace, out_dir: Path, run_dir: Path, command: str,
                     config: dict[str, Any], corpus: Corpus | None = None) -> Path:
    """``MODEL_CARD.md`` beside the checkpoints, from the held-out evaluation of ``run_dir``."""
    from models.card import model_card
    from reports.completion import read_completion_categories
    from reports.tables import markdown_table

    notes = ["## Held-out IoU (%) by origin of the parts, one view", "",
             markdown_table(origin_table(ws, run_dir)), "",
             f"Held-out report of this training: `{run_dir.name}` of the training workspace."]
    if corpus is not None:
        notes = [corpus_note(corpus), "", *notes]
    text = model_card(out_dir, dataset_table(ws), read_completion_categories(run_dir), command,
                      notes=notes, config=config)
    path = out_dir / "MODEL_CARD.md"
    path.write_text(text)
    return path


# ---------------------------------------------------------------- the train flow


@task(name="prepare-corpus")
def corpus_task(workspace: str, shared: str | None, variants: int, seed: int,
                workers: int) -> Corpus:
    """The training corpus: library with variants, shared parts, ingest, scenes, shots."""
    ingest_cfg = IngestConfig(limits=Limits(workers=workers, seconds=600))
    return prepare_corpus(Workspace(Path(workspace)), Path(shared) if shared else None,
                          variants, seed, ingest_cfg, CorpusConfig(seed=seed))


@task(name="train-model")
def train_task(workspace: str, method: str, protocol: str, steps: int, out: str) -> Trained:
    """One method on one protocol; the best checkpoint into ``out``."""
    return train_model(Workspace(Path(workspace)), method, protocol, steps, Path(out))


@task(name="evaluate-models")
def evaluate_task(workspace: str, out: str, run_dir: str) -> str:
    """Held-out scores of every method into the run's completion report."""
    evaluate_models(Workspace(Path(workspace)), Path(out), Path(run_dir))
    return run_dir


@task(name="relation-dataset")
def relation_dataset_task(workspace: str, completion: str, workers: int) -> dict[str, int]:
    """Labels of the corpus's pairs and the relation dataset completed by ``completion``."""
    from flows.train_relations import build_dataset

    return build_dataset(Workspace(Path(workspace)), Path(completion),
                         Limits(workers=workers, seconds=600))


@task(name="train-relation-model")
def train_relation_task(workspace: str, method: str, name: str, steps: int,
                        out: str) -> dict[str, Any]:
    """One relation method on one input; the best checkpoint into ``out``."""
    from flows.train_relations import train_relation_model

    return asdict(train_relation_model(Workspace(Path(workspace)), method, name, steps,
                                       Path(out)))


@task(name="evaluate-relations")
def evaluate_relations_task(workspace: str, out: str, run_dir: str, command: str,
                            config: dict[str, Any]) -> str:
    """Held-out relation report of every method and input, and the relation model card."""
    from flows.train_relations import evaluate_relations, write_relation_card

    ws = Workspace(Path(workspace))
    evaluate_relations(ws, Path(out), Path(run_dir))
    return str(write_relation_card(ws, Path(out), Path(run_dir), command, config))


@flow(name="train")
def train(workspace: str = "train-workspace", shared: str | None = None, variants: int = 100,
          seed: int = 0, steps: int = 2000, methods: list[str] | None = None,
          protocols: list[str] | None = None, out: str | None = None,
          workers: int = 2, relation_steps: int = 1000,
          relation_out: str | None = None) -> dict[str, Any]:
    """Train the completion checkpoints, then the relation checkpoints on the same corpus, and
    write their held-out reports and model cards.

    Args:
        workspace: the training workspace (corpus, dataset, resumable snapshots, runs).
        shared: a folder of real STEP parts added to the corpus (split by part).
        variants: parametric variants per category of the sample library.
        steps: training steps per completion model (a rerun resumes unfinished ones).
        methods, protocols: which completion checkpoints (default: all three, both protocols).
        out: where the completion checkpoints and MODEL_CARD.md go (default: the workspace's
            ``checkpoints/completion``; ``mateqa ship completion`` makes them the default).
        workers: worker processes for the CAD and rendering work.
        relation_steps: training steps per relation model (0: no relation training).
        relation_out: where the relation checkpoints and their MODEL_CARD.md go (default: the
            workspace's ``checkpoints/relations``; ``mateqa ship relations`` ships them).
    """
    log = get_run_logger()
    ws = Workspace(Path(workspace).resolve())
    out = out or str(ws.checkpoints("completion"))
    relation_out = relation_out or str(ws.checkpoints("relations"))
    corpus = corpus_task(str(ws.root), shared, variants, seed, workers)
    log.info("corpus: %d parts %s, %d failed", corpus.parts, corpus.splits, corpus.failed)
    trained = [train_task(str(ws.root), m, p, steps, out)
               for p in protocols or list(PROTOCOLS) for m in methods or list(LEARNED)]
    for t in trained:
        log.info("%s/%s: best val IoU %.3f at step %d (%.0f s)", t.method, t.protocol,
                 t.val_iou, t.step, t.seconds)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    run_dir = ws.run_dir(stamp)
    evaluate_task(str(ws.root), out, str(run_dir))
    card = write_model_card(ws, Path(out), run_dir, f"prefect flow train(workspace={workspace!r}"
                            f", shared={shared!r}, variants={variants}, steps={steps})",
                            {"steps": steps, "variants": variants, "seed": seed}, corpus)
    result: dict[str, Any] = {"corpus": asdict(corpus), "trained": [asdict(t) for t in trained],
                              "report": str(run_dir), "card": str(card)}
    if relation_steps > 0:
        rows = relation_dataset_task(str(ws.root), out, workers)
        log.info("relation pair views per split: %s", rows)
        relations = [train_relation_task(str(ws.root), m, name, relation_steps, relation_out)
                     for name in INPUTS for m in ("ltn", "mlp")]
        rel_dir = ws.run_dir(f"relations-{stamp}")
        result["relations"] = relations
        result["relation_card"] = evaluate_relations_task(
            str(ws.root), relation_out, str(rel_dir),
            f"prefect flow train(workspace={workspace!r}, relation_steps={relation_steps})",
            {"steps": relation_steps, "seed": seed})
        result["relation_report"] = str(rel_dir)
    return result
