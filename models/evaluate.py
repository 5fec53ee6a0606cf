"""Completing parts with every method and scoring them against the truth, in one harness.

Every registered completion method (``models.completions``) sees the same examples (same
parts, same views, same grid): the methods without learning complete from what each example
carries, the learned ones from the checkpoints of a folder (one per method and protocol, the
protocol read from each checkpoint's ``data``). Every prediction is scored by
``reports.completion`` (one row per part, method, protocol, number of views and first view),
and the shipped method's completion is registered onto the example's observed points by ICP
(``cadio.capture.register``): its residual says how well the completed shape explains the
scan, in the part's millimetres.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pandas as pd
import torch

from cadio.capture.coverage import capture_context
from cadio.capture.examples import Example, read_example
from cadio.capture.register import register
from cadio.catalog import read_catalog
from cadio.inspect.completion import LibraryCad
from cadio.sandbox import Job, Limits, run_isolated
from cadio.workspace import Workspace, atomic_path
from models.checkpoint import load_checkpoint, model_from_checkpoint
from models.completions import COMPLETIONS, CompletionMethod, ours
from models.train import Model, predict
from reports.completion import CompletionCase, parts_frame, write_completion
from reports.coverage import part_coverage, write_part_coverage
from reports.headline import headline_markdown, headline_table, write_headline
from reports.metrics import Truth, surface_points
from reports.shapes import GEOMETRY_COLUMNS
from reports.tables import markdown_table

log = logging.getLogger(__name__)

# The checkpoints shipped with the package (see their MODEL_CARD.md): the nightly needs no
# training.
SHIPPED = Path(__file__).resolve().parent / "checkpoints" / "completion"
THRESHOLD = 0.5  # probability above which a voxel is solid (as validation IoU is measured)


@dataclass(frozen=True)
class CompletionModels:
    """Loaded checkpoints by (method, protocol), and what each says about itself."""

    models: dict[tuple[str, str], Model]
    cards: dict[tuple[str, str], dict[str, Any]]

    def versions(self) -> dict[str, str]:
        """"method/protocol" -> "step N, code <version>" for the report."""
        return {f"{m}/{p}": f"step {c['step']}, code {c['code_version']}"
                for (m, p), c in sorted(self.cards.items())}

    def trained_on(self) -> set[str]:
        """Part ids any of the checkpoints was trained on (never held out for them)."""
        return {pid for c in self.cards.values() for pid in c.get("data", {}).get("train_parts",
                                                                                 [])}


def load_models(folder: Path = SHIPPED, device: str = "cpu") -> CompletionModels:
    """Every ``*.pt`` checkpoint of ``folder`` (weights only), by method and protocol; none
    when the folder does not exist (then only the baselines without learning run).

    Raises:
        CheckpointError: a file is not a completion checkpoint.
    """
    models, cards = {}, {}
    for path in sorted(Path(folder).glob("*.pt")) if Path(folder).is_dir() else []:
        ckpt = load_checkpoint(path)
        key = (str(ckpt["method"]), str(ckpt["data"].get("protocol", "observed")))
        models[key] = model_from_checkpoint(ckpt).to(torch.device(device))
        cards[key] = {k: v for k, v in ckpt.items() if k not in ("state_dict", "train_state")}
    return CompletionModels(models, cards)


def complete(models: CompletionModels, example: Example, cad: LibraryCad | None = None,
             learned: Mapping[str, npt.NDArray[np.bool_]] | None = None
             ) -> dict[str, npt.NDArray[np.bool_]]:
    """Every registered method's solid for one example (``models.completions``); a learned
    method without a checkpoint for the example's protocol is left out, and so is one that
    reads the library's CAD where ``cad`` has none of the example's capture (or is None), or
    where it fails on the example (logged: the other methods' solids stand). ``learned``: the
    learned methods' solids of the example where they were predicted already (``learned_solids``,
    several examples to a forward pass); None: predicted here."""
    if learned is None:
        learned = learned_solids(models, [example])[0]
    out = {}
    for method in COMPLETIONS.entries():
        if method.solid is not None:
            out[method.name] = method.solid(example)
            continue
        if method.from_cad is not None:
            scene = None if cad is None else cad.of(str(example.meta.get("capture", "")))
            if scene is not None:
                try:
                    out[method.name] = method.from_cad(example, scene)
                except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
                    # one example's registration, not the batch: its other methods stand
                    log.warning("%s of %s in %s: %s: %s", method.name,
                                example.meta.get("part_id"), example.meta.get("capture"),
                                type(exc).__name__, exc)
            continue
        if method.name in learned:
            out[method.name] = learned[method.name]
    return out


# Examples to a forward pass of a learned completion (a folder's: a part in one context, its
# single views and sequences, both protocols). On one thread, the three networks over 88
# examples of four held-out folders: 3.5-3.6 s one at a time, 2.8 s two at a time, 2.9 s
# four, 3.5-3.7 s eight (the larger passes' activations leave the caches).
PREDICT_BATCH = 2


def learned_solids(models: CompletionModels, examples: Sequence[Example]
                   ) -> list[dict[str, npt.NDArray[np.bool_]]]:
    """Each learned method's solid for each example that a checkpoint of its protocol
    completes, several examples to a forward pass (``PREDICT_BATCH``)."""
    out: list[dict[str, npt.NDArray[np.bool_]]] = [{} for _ in examples]
    for method in COMPLETIONS.entries():
        if method.model_input is None:
            continue
        for protocol in dict.fromkeys(e.protocol for e in examples):
            model = models.models.get((method.name, protocol))
            if model is None:
                continue
            chosen = [i for i, e in enumerate(examples) if e.protocol == protocol]
            probs = predict(model, [method.model_input(examples[i]) for i in chosen],
                            batch_size=PREDICT_BATCH)
            for i, prob in zip(chosen, probs, strict=True):
                out[i][method.name] = prob > THRESHOLD
    return out


@dataclass(frozen=True)
class RegistrationRow:
    """ICP of one completion onto its scan: residual and fitness, part millimetres."""

    part_id: str
    protocol: str
    n_views: int
    view_deg: float
    fitness: float
    residual_mm: float


def context_of(meta: Mapping[str, Any]) -> str:
    """Where an example's part was seen: the corpus says it (``kind``); a nightly capture by its
    name (``cadio.capture.coverage.capture_context``)."""
    if "kind" in meta:
        return str(meta["kind"])
    return capture_context(str(meta.get("capture", "")))


def score_example(example: Example, preds: Mapping[str, npt.NDArray[np.bool_]],
                  split: str, category: str) -> list[dict[str, Any]]:
    """One ``completion_parts`` row per method for an example with a target."""
    if example.target is None:
        return []
    truth = Truth(example.target, example.voxel_mm)  # prepared once for every method
    rows = []
    for method, pred in preds.items():
        case = CompletionCase(part_id=str(example.meta["part_id"]), category=category,
                              split=split, method=method, protocol=example.protocol,
                              n_views=len(example.views), view_deg=example.azimuths[0] % 360,
                              context=context_of(example.meta), coverage=example.coverage)
        rows.append(case.score(pred, truth, example.voxel_mm))
    return rows


def register_completion(example: Example, solid: npt.NDArray[np.bool_],
                        n_out: int) -> RegistrationRow:
    """ICP of the completion's surface onto the example's observed points."""
    voxel_m = example.grid.voxel_m(n_out)  # surface_points works in any unit: metres here
    surface = surface_points(solid, voxel_m, example.grid.grid_to_world(n_out))
    mm_per_world = example.voxel_mm / example.grid.voxel_m(n_out)
    fit, residual = 0.0, math.nan
    if len(surface) and len(example.points):
        result = register(surface, example.points, 3 * example.grid.voxel_m(n_out))
        fit, residual = result.fitness, result.residual * mm_per_world
    return RegistrationRow(str(example.meta["part_id"]), example.protocol, len(example.views),
                           example.azimuths[0] % 360, fit, residual)


@dataclass(frozen=True)
class Scores:
    """The rows of ``completion_parts`` and of the registration table, and failures."""

    parts: list[dict[str, Any]]
    registration: list[dict[str, Any]]
    failed: list[tuple[str, str]]


def score_files(paths: Iterable[Path], models: CompletionModels,
                split_of: Callable[[str], str], category_of: Callable[[str], str],
                on_file: Callable[[str], None] | None = None,
                cad: LibraryCad | None = None) -> Scores:
    """Complete and score every example file; a file that cannot be read or scored (an empty
    truth grid, a network's error) is a failure row of its own, and the others are scored.
    ``cad``: the library's CAD of the examples' captures, for the methods that read it."""
    parts: list[dict[str, Any]] = []
    registration: list[dict[str, Any]] = []
    failed: list[tuple[str, str]] = []
    for group in _by_folder(paths):
        examples: list[tuple[Path, Example]] = []
        for path in group:
            try:
                examples.append((path, read_example(path)))
            except (OSError, ValueError, KeyError) as exc:
                log.warning("completion of %s: %s: %s", path, type(exc).__name__, exc)
                failed.append((str(path), f"{type(exc).__name__}: {exc}"))
        try:
            learned: list[dict[str, npt.NDArray[np.bool_]] | None] = list(
                learned_solids(models, [e for _, e in examples]))
        except (ValueError, RuntimeError):  # an example a network refuses: each on its own
            learned = [None] * len(examples)
        for (path, example), solids in zip(examples, learned, strict=True):
            try:
                pid = str(example.meta["part_id"])
                preds = complete(models, example, cad, solids)
                rows = score_example(example, preds, split_of(pid), category_of(pid))
                if ours().name in preds and example.target is not None:
                    registration.append(asdict(register_completion(
                        example, preds[ours().name], example.target.shape[0])))
            except (OSError, ValueError, KeyError, RuntimeError) as exc:
                log.warning("completion of %s: %s: %s", path, type(exc).__name__, exc)
                failed.append((str(path), f"{type(exc).__name__}: {exc}"))
                continue
            parts += rows
            if on_file is not None:
                on_file(str(path))
    return Scores(parts, registration, failed)


def _by_folder(paths: Iterable[Path], most: int = 32) -> list[list[Path]]:
    """``paths`` in runs of the same folder, in their order, at most ``most`` a run (a
    corpus's flat folder of thousands is not read at once)."""
    runs: list[list[Path]] = []
    for path in paths:
        if runs and Path(runs[-1][-1]).parent == Path(path).parent and len(runs[-1]) < most:
            runs[-1].append(path)
        else:
            runs.append([path])
    return runs


def part_inputs(captures: Iterable[Path]) -> list[Path]:
    """The input folder of each part in each context (alone, in a pair, inside an assembly) in
    the first capture (by name) that shows it there: a part in several scenes is scored once
    per context, as ``completion_parts`` has one row per part, context and view. A folder is
    one instance of a capture; its part is the one its examples name. A folder of a part its
    capture does not score (only the views' inputs, ``cadio.capture.scan.scan_inputs``) is
    passed over."""
    first: dict[tuple[str, str], Path] = {}
    for capture in sorted(c for c in captures if Path(c).is_dir()):
        for folder in sorted(p for p in Path(capture).iterdir() if p.is_dir()):
            meta = folder_meta(folder)
            if meta is not None and not meta.get("input_only"):
                first.setdefault((str(meta["part_id"]), context_of(meta)), folder)
    return [first[k] for k in sorted(first)]


def folder_meta(folder: Path) -> dict[str, Any] | None:
    """The meta of one example of an input folder (None when it holds none readable)."""
    for path in sorted(folder.glob("*-*.npz")):
        try:
            with np.load(path) as z:
                return dict(json.loads(str(z["meta"])))
        except (OSError, ValueError, KeyError):
            continue
    return None


def complete_parts(folders: Iterable[Path], models_dir: Path, ws: Workspace) -> Scores:
    """The completion stage of the nightly for some parts' input folders.

    A part is held out ("test") unless a checkpoint was trained on it ("train"); its category
    is the catalog's.
    """
    models = load_models(models_dir)
    seen = models.trained_on()
    catalog = read_catalog(ws.catalog)
    category = dict(zip(catalog["part_id"].astype(str), catalog["category"].astype(str),
                        strict=True))
    paths = [p for folder in folders for p in sorted(Path(folder).glob("*-*.npz"),
                                                     key=_views_first)]
    return score_files(paths, models, lambda pid: "train" if pid in seen else "test",
                       lambda pid: category.get(pid, "unknown"), cad=LibraryCad(ws))


@dataclass(frozen=True)
class CompleteJob:
    """One batch of the completion stage, as a worker process runs it."""

    folders: tuple[str, ...]
    models_dir: str
    workspace: str
    methods: tuple[CompletionMethod, ...] = ()  # registered outside ``models.completions``


def complete_job(job: CompleteJob) -> Scores:
    with COMPLETIONS.including(job.methods):
        return complete_parts([Path(f) for f in job.folders], Path(job.models_dir),
                              Workspace(Path(job.workspace)))


# A batch is minutes of registration (Python between numpy calls) beside the networks: in a
# worker process of its own, two batches run on two cores, where in the night's two threads
# they shared one interpreter's lock; each worker on one thread of its libraries (torch's
# too: ``OMP_NUM_THREADS``), as the inspection's.
ISOLATED = Limits(seconds=3600.0, memory_mb=8192, workers=1, threads=1)


def complete_isolated(folders: Sequence[Path], models_dir: Path, ws: Workspace,
                      limits: Limits = ISOLATED) -> Scores:
    """``complete_parts`` in a worker process (``cadio.sandbox``); a worker that dies or runs
    out of time fails each of the batch's folders, with the reason, and the night goes on."""
    job = CompleteJob(tuple(str(f) for f in folders), str(models_dir), str(ws.root),
                      COMPLETIONS.foreign())
    (outcome,) = run_isolated(complete_job, [Job(str(models_dir), job)], limits)
    if outcome.result is not None:
        return outcome.result
    log.warning("completion of %d part folders: %s", len(folders), outcome.error)
    return Scores([], [], [(str(f), f"completion worker: {outcome.error}") for f in folders])


def _views_first(path: Path) -> tuple[int, str]:
    """An input folder's examples, single views first (the registered completion starts a
    sequence from its views' own registrations): ``observed-0-4`` has two views."""
    return sum(token.isdigit() for token in path.stem.split("-")), path.name


def write_completion_report(run_dir: Path, scores: Iterable[Scores],
                            ingested: pd.DataFrame | None = None,
                            geometry: pd.DataFrame | None = None) -> Path:
    """``completion_parts.parquet``, ``completion_categories.csv``, ``completion.md`` and
    ``completion_registration.csv`` of the scores, with ``ingested`` (the library's parts:
    part_id, category) ``completion_coverage.csv``, and ``completion_headline.csv`` (per
    distinct shape of ``geometry``, ``reports.shapes.part_geometry``: without it each part is
    a shape and a file of its own); returns the Markdown's path."""
    batches = list(scores)
    parts = parts_frame(row for s in batches for row in s.parts)
    library = None if ingested is None else part_coverage(parts, ingested)
    if library is not None:
        write_part_coverage(run_dir, library)
    md = write_completion(run_dir, parts, library)
    headline = headline_table(parts, pd.DataFrame(columns=list(GEOMETRY_COLUMNS))
                              if geometry is None else geometry)
    write_headline(run_dir, headline)
    with md.open("a") as fh:
        fh.write(headline_markdown(headline))
    registration = pd.DataFrame([r for s in batches for r in s.registration],
                                columns=[f.name for f in fields(RegistrationRow)])
    with atomic_path(run_dir / "completion_registration.csv") as tmp:
        registration.to_csv(tmp, index=False)
    failed = [f for s in batches for f in s.failed]
    if failed or len(registration):
        with md.open("a") as fh:
            fh.write(_registration_markdown(registration, failed))
    return md


def _registration_markdown(registration: pd.DataFrame, failed: list[tuple[str, str]]) -> str:
    lines = ["", "## Registration of the completions onto the scans (ICP)", ""]
    if len(registration):
        by = registration.groupby("protocol")
        table = pd.DataFrame({"parts": by["part_id"].nunique(),
                              "median residual mm": by["residual_mm"].median().round(3),
                              "mean fitness": by["fitness"].mean().round(3)}).reset_index()
        lines.append(markdown_table(table))
    for path, reason in failed:
        lines.append(f"- {path}: {reason}")
    return "\n".join(lines) + "\n"
