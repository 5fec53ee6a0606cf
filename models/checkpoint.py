"""Self-describing checkpoints of the completion models, safe to load with ``weights_only``.

A checkpoint is a plain dict of plain values and tensors (so ``torch.load(path,
weights_only=True)`` reads it without running any code from the file)::

    format        "mateqa.checkpoint/1"
    method        "gan_lstm" | "ae" | "gan" | "lstm" | "r2n2"
    config        the method's config dataclass as a plain dict: it alone rebuilds the module
    state_dict    the model's weights; float16 on disk when ``precision`` says so (halves a
                  shipped file; converted back to float32 on load)
    precision     "float16" | "float32"
    step          training steps done
    metrics       floats (validation IoU, losses, ...) at that step
    code_version  package version + a hash of the models/ sources
    data          what the caller says about the data (split sizes, sources)
    created       ISO-8601 UTC time
    train_state   only in resumable snapshots: critic weights, optimiser states, history and
                  the best checkpoint so far (float32 throughout, so a resume is exact)
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import pickle
import re
import shutil
from collections.abc import Mapping
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

import torch
from torch import nn

from cadio.errors import InputFileError
from cadio.inputs import open_regular
from cadio.workspace import create_beside
from models.baselines import R2N2, R2N2Config
from models.completion import CompletionConfig, Generator
from models.errors import CheckpointError

FORMAT = "mateqa.checkpoint/1"
KEYS = ("format", "method", "config", "state_dict", "precision", "step", "metrics",
        "code_version", "data", "created")

Config = CompletionConfig | R2N2Config
Checkpoint = dict[str, Any]


def code_version() -> str:
    """``<package version>+<first 12 hex of a SHA-256 over models/*.py>``. The version is the
    installed package's, or where it is not installed (a copy of the tree on a GPU machine)
    that of the tree's ``pyproject.toml``; ``unknown`` where neither says."""
    try:
        version = metadata.version("mateqa")
    except metadata.PackageNotFoundError:
        version = _tree_version(Path(__file__).resolve().parents[1] / "pyproject.toml")
    digest = hashlib.sha256()
    for path in sorted(Path(__file__).parent.glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return f"{version}+{digest.hexdigest()[:12]}"


def _tree_version(pyproject: Path) -> str:
    """``[project] version`` of a ``pyproject.toml``, or ``unknown``."""
    import tomllib

    try:
        version = tomllib.loads(pyproject.read_text())["project"]["version"]
    except (OSError, tomllib.TOMLDecodeError, KeyError, TypeError):
        return "unknown"
    return str(version)


def config_from_dict(method: str, config: Mapping[str, Any]) -> Config:
    """The config dataclass of ``method`` from its plain dict.

    Raises:
        ValueError: unknown fields, bad values, or a config of another method.
    """
    from models.completions import COMPLETIONS, ours

    # a method the registry lacks is an ablation of ours (``gan``, ``lstm``): ours' config
    spec = COMPLETIONS.get(method) if method in COMPLETIONS else ours()
    try:
        cfg: Config = spec.make_config(**config)
    except ValueError as exc:
        raise ValueError(f"config does not fit method {method!r}: {exc}") from exc
    if cfg.method != method:
        raise ValueError(f"config describes method {cfg.method!r}, not {method!r}")
    return cfg


def build_model(cfg: Config) -> Generator | R2N2:
    """A freshly initialised module for ``cfg`` (uses torch's global RNG)."""
    return R2N2(cfg) if isinstance(cfg, R2N2Config) else Generator(cfg)


def _plain(value: Any, what: str) -> Any:
    """A JSON round trip: only plain containers of str, numbers, bools and None pass."""
    try:
        return json.loads(json.dumps(value, allow_nan=True))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must hold only plain values: {exc}") from exc


def state_copy(module: nn.Module, half: bool) -> dict[str, torch.Tensor]:
    """A detached CPU copy of the module's weights, float tensors in float16 when ``half``."""
    out = {}
    for k, v in module.state_dict().items():
        v = v.detach().to("cpu", copy=True)
        out[k] = v.half() if half and v.is_floating_point() else v
    return out


def make_checkpoint(model: Generator | R2N2, step: int, metrics: Mapping[str, float],
                    data: Mapping[str, Any] | None = None, half: bool = True,
                    train_state: Mapping[str, Any] | None = None) -> Checkpoint:
    """The checkpoint dict of ``model`` (weights copied, so later training leaves it alone)."""
    ckpt: Checkpoint = {
        "format": FORMAT,
        "method": model.cfg.method,
        "config": dataclasses.asdict(model.cfg),
        "state_dict": state_copy(model, half),
        "precision": "float16" if half else "float32",
        "step": int(step),
        "metrics": {k: float(v) for k, v in metrics.items()},
        "code_version": code_version(),
        "data": _plain(dict(data or {}), "data"),
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    if train_state is not None:
        ckpt["train_state"] = dict(train_state)
    return ckpt


def model_from_checkpoint(ckpt: Mapping[str, Any]) -> Generator | R2N2:
    """Rebuild the module from the checkpoint's method and config, load float32 weights, eval.

    Raises:
        CheckpointError: another format, or weights that do not fit the config.
    """
    where = str(ckpt.get("created", "<checkpoint>"))
    if ckpt.get("format") != FORMAT or any(k not in ckpt for k in KEYS):
        raise CheckpointError(where, f"not a {FORMAT} checkpoint")
    try:
        model = build_model(config_from_dict(ckpt["method"], ckpt["config"]))
        weights = {k: v.float() if v.is_floating_point() else v
                   for k, v in ckpt["state_dict"].items()}
        model.load_state_dict(weights)
    except (ValueError, RuntimeError) as exc:
        raise CheckpointError(where, f"weights do not fit the config: {exc}") from exc
    return model.eval()


def save_checkpoint(ckpt: Mapping[str, Any], path: Path | str) -> Path:
    """Write atomically (temp file + rename) and return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = create_beside(path, ".pt.tmp")  # mode as the umask gives, like any written file
    with os.fdopen(fd, "wb") as f:
        torch.save(dict(ckpt), f)
    os.replace(tmp, path)
    return path


def load_checkpoint(path: Path | str) -> Checkpoint:
    """Read a checkpoint with ``weights_only=True`` and check its format.

    Raises:
        CheckpointError: unreadable, not loadable as weights only, or another format.
    """
    try:
        with open_regular(path) as fh:
            ckpt = torch.load(fh, map_location="cpu", weights_only=True)
    except InputFileError as exc:
        raise CheckpointError(path, exc.reason) from None
    except OSError as exc:
        raise CheckpointError(path, f"cannot be read: {exc.strerror or exc}") from None
    except Exception as exc:  # bytes that are no checkpoint: torch's unpickler raises anything
        raise CheckpointError(path, f"not a checkpoint (damaged, or not weights and plain "
                              f"values only: {_unpickling_reason(exc)})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise CheckpointError(path, f"not a {FORMAT} checkpoint")
    missing = [k for k in KEYS if k not in ckpt]
    if missing:
        raise CheckpointError(path, f"missing keys {missing}")
    return ckpt


def _unpickling_reason(exc: Exception) -> str:
    """The reason of a failed weights-only load, without torch's advice to load the file
    with ``weights_only=False`` (which would run the code a hostile file holds)."""
    text = str(exc)
    found = re.search(r"WeightsUnpickler error:\s*(.+?)\s*(?:\n\n|$)", text, re.S)
    if found:  # e.g. "Unsupported global: GLOBAL numpy...", without how to allow it
        return found.group(1).splitlines()[0].split(" was not an allowed global")[0]
    if isinstance(exc, pickle.UnpicklingError) or "weights_only" in text:
        return "its pickle holds more than tensors and plain values"
    first = text.splitlines()[0] if text else ""
    return f"{type(exc).__name__}: {first}" if first else type(exc).__name__


def ship_checkpoints(trained: Path, shipped: Path) -> list[Path]:
    """Copy a folder of trained checkpoints and its ``MODEL_CARD.md`` over the shipped ones.

    ``mateqa train`` writes into its workspace; shipping is the explicit step that makes them
    what a night uses by default. Each file is copied atomically (temp file + rename); shipped
    checkpoints of methods that were not trained stay.

    Returns:
        The shipped files.

    Raises:
        CheckpointError: ``trained`` holds no checkpoint.
    """
    files = sorted(trained.glob("*.pt"))
    if not files:
        raise CheckpointError(trained, "no checkpoint (*.pt) to ship: train into it first")
    card = trained / "MODEL_CARD.md"
    shipped.mkdir(parents=True, exist_ok=True)
    out = []
    for src in [*files, *([card] if card.is_file() else [])]:
        fd, tmp = create_beside(shipped / src.name)
        with os.fdopen(fd, "wb") as dst, src.open("rb") as f:
            shutil.copyfileobj(f, dst)
        os.replace(tmp, shipped / src.name)
        out.append(shipped / src.name)
    return out


def model_card(ckpt: Mapping[str, Any], command: str = "") -> str:
    """A short Markdown model card: method, config, size, metrics, data, code version, command."""
    n = sum(v.numel() for v in ckpt["state_dict"].values())
    lines = [f"# {ckpt['method']} completion model", "",
             f"- step {ckpt['step']}, {n:,} weights ({ckpt['precision']} on disk), "
             f"code {ckpt['code_version']}, created {ckpt['created']}",
             f"- metrics: {_pairs(ckpt['metrics'])}",
             f"- data: {_pairs(ckpt['data'])}",
             f"- config: {_pairs(ckpt['config'])}"]
    if command:
        lines += ["", "Trained with:", "", f"    {command}"]
    return "\n".join(lines) + "\n"


def _pairs(values: Mapping[str, Any]) -> str:
    return ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                     for k, v in values.items())

