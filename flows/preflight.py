"""What a night's configuration must hold before any work starts, beyond its schema.

``check_night`` looks at the files a ``NightConfig`` names: the workspace can be a folder and
is one mateqa may fill (new, empty or a workspace already; never ``/`` or a system folder), the
library has STEP files and every category asked for, the recordings folder holds recordings,
each model folder holds checkpoints that load (weights only), and the thresholds file reads.
A night that would check nothing (no file, no category, no model) fails here with that reason
instead of passing green; every problem names its field. The CLI calls it before it starts a
server (exit 2), and the nightly flow again first thing, so a deployment run fails the same way.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from cadio.cad.ingest import STEP_SUFFIXES, discover
from cadio.errors import InputFileError
from cadio.records import Category
from cadio.workspace_claim import workspace_problem
from flows.config import ConfigError, NightConfig

# The folders of the built-in sample library (cadio.samples.library, not imported: it loads
# build123d, seconds before any check could answer).
SAMPLE_CATEGORIES = (*Category.paper(), "assemblies")

Problems = list[tuple[str, str]]


def check_night(cfg: NightConfig) -> list[str]:
    """Check what ``cfg`` names on disk; the warnings (the night can run, but should say so).

    Raises:
        ConfigError: every problem found, each with its field and the reason.
    """
    problems: Problems = []
    warnings: list[str] = []
    check_workspace(cfg.runtime.workspace, "runtime.workspace", problems)
    check_own_workspace(cfg.runtime.workspace, "runtime.workspace", problems)
    warnings += _check_library(cfg, problems)
    _check_recordings(cfg.capture.recordings, problems)
    _check_thresholds(cfg.thresholds.file, problems)
    if not problems:  # loading the checkpoints takes seconds: only when the rest holds
        _check_models(cfg, problems)
    if problems:
        raise ConfigError(problems)
    return warnings


def check_workspace(workspace: str | Path, field: str, problems: Problems) -> None:
    """A folder the run can write: an existing folder, or one that can be made in a writable
    folder (nothing is made here)."""
    path = Path(workspace)
    if path.exists() and not path.is_dir():
        problems.append((field, f"{path} is a file, not a folder"))
        return
    parent = path
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        problems.append((field, f"{path} cannot be made: {parent} is not a folder"))
    elif not os.access(parent, os.W_OK | os.X_OK):
        problems.append((field, f"{path}: {parent} is not writable"))


def check_own_workspace(workspace: str | Path, field: str, problems: Problems) -> None:
    """A folder mateqa may fill: new, empty or a workspace already, never the filesystem's
    root or a system folder, and no folder where ``runs/latest`` should link
    (``cadio.workspace_claim.workspace_problem``)."""
    problem = workspace_problem(workspace)
    if problem:
        problems.append((field, problem))


def check_finished_run(workspace: str | Path, run: str, problems: Problems) -> None:
    """A run folder with its ``summary.json`` (written last: a run without it did not
    complete, and its predictions may be partial)."""
    root = Path(workspace)
    if not root.is_dir():
        problems.append(("workspace", f"{root} is not a folder"))
        return
    folder = root / "runs" / run
    if not folder.is_dir():
        runs = sorted(p.name for p in (root / "runs").glob("2*"))
        problems.append(("run", f"no run {run!r} in {root / 'runs'} (the last ones: "
                         f"{', '.join(runs[-3:]) or 'none'})"))
    elif not (folder / "summary.json").is_file():
        problems.append(("run", f"{folder.resolve()} did not complete (no summary.json): its "
                         "predictions may be partial; export a finished run"))


def _check_library(cfg: NightConfig, problems: Problems) -> list[str]:
    wanted = cfg.library.categories
    if cfg.library.path is None:
        present: set[str] = set(SAMPLE_CATEGORIES)
        where = "the built-in sample library"
        warnings = []
    else:
        root = Path(cfg.library.path)
        try:
            found = discover(root)
        except InputFileError as exc:
            problems.append(("library.path", str(exc)))
            return []
        if not found:
            problems.append(("library.path", f"{root}: no STEP file (*.step, *.stp) found: "
                             "the night would check nothing"))
            return []
        present, where = {f.category for f in found}, str(root)
        warnings = _empty_folders(root, present)
    unknown = sorted(set(wanted or ()) - present)
    if unknown:
        problems.append(("library.categories", f"{', '.join(map(repr, unknown))} not in "
                         f"{where} (its categories: {', '.join(sorted(present))})"))
    return warnings


def _empty_folders(root: Path, present: set[str]) -> list[str]:
    """Category folders of a library folder that hold no STEP file (a copy that went wrong)."""
    if not root.is_dir():
        return []
    return [f"{root / d.name}: category folder with no STEP file ({'/'.join(STEP_SUFFIXES)})"
            for d in sorted(root.iterdir())
            if d.is_dir() and not d.name.startswith(".") and d.name not in present]


def _check_recordings(recordings: str | None, problems: Problems) -> None:
    if recordings is None:
        return
    folder = Path(recordings)
    if not folder.is_dir():
        problems.append(("capture.recordings", f"{folder} is not a folder"))
    elif not any(p.is_file() for p in folder.rglob("*.mcap")):
        problems.append(("capture.recordings", f"{folder}: no recording (*.mcap file) found: "
                         "the night would check nothing"))


def _check_models(cfg: NightConfig, problems: Problems) -> None:
    from models.evaluate import SHIPPED
    from models.relate import SHIPPED_RELATIONS

    _check_model_folder("models.completion", Path(cfg.models.completion or SHIPPED),
                        _completion_errors, problems)
    _check_model_folder("models.relations", Path(cfg.models.relations or SHIPPED_RELATIONS),
                        _relation_errors, problems)


def _check_model_folder(field: str, folder: Path, errors: Callable[[Path], list[str]],
                        problems: Problems) -> None:
    if not folder.is_dir():
        problems.append((field, f"{folder} is not a folder"))
    elif not any(p.is_file() for p in folder.glob("*.pt")):
        problems.append((field, f"{folder}: no checkpoint (*.pt) found: the learned methods "
                         "would be left out"))
    else:
        problems.extend((field, e) for e in errors(folder))


def _completion_errors(folder: Path) -> list[str]:
    from models.checkpoint import load_checkpoint, model_from_checkpoint
    from models.errors import CheckpointError

    out = []
    for path in sorted(folder.glob("*.pt")):
        try:
            model_from_checkpoint(load_checkpoint(path))
        except CheckpointError as exc:
            out.append(f"{path}: {exc.reason}")
    return out


def _relation_errors(folder: Path) -> list[str]:
    from models.relate import load_relation_models

    return [f"{folder / e}" for e in load_relation_models(folder).errors]


def _check_thresholds(path: str | None, problems: Problems) -> None:
    from reports.trends import DEFAULT_THRESHOLDS, ThresholdsError, read_thresholds

    try:
        read_thresholds(Path(path) if path else DEFAULT_THRESHOLDS)
    except ThresholdsError as exc:
        problems.append(("thresholds.file", str(exc)))
