"""Training the completion networks on the corpus, their held-out scores and model card.

``train_model`` trains one learned method on one protocol of the corpus
(``models.training.prepare``), resumable; ``evaluate_models`` scores every method on the
held-out split beside the baselines (``models.evaluate``); ``write_model_card`` writes the card
from that report. ``mateqa train completion`` and the ``train`` flow both run these steps.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from cadio.catalog import read_catalog
from cadio.workspace import Workspace
from models.training.corpus import (
    read_index,
)
from models.training.prepare import (
    Corpus,
    Progress,
    corpus_library,
    corpus_note,
    dataset_dir,
)


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
    if not getattr(config_for(method), "gan", False):  # only a critic has its own rate
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
