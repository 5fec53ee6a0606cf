"""Typed records the stages hand to each other and to the reports.

Each stage of the nightly flow returns small summaries, never big arrays (those stay in the
workspace, addressed by path). The summaries that cross into ``reports/`` live here, in a
module that imports nothing heavy, so a report never pulls in a CAD kernel. Job payloads that
only one stage reads stay with that stage (``cadio.cad.ingest.IngestJob``,
``cadio.truth.mates.AssemblyJob``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any


@dataclass(frozen=True)
class MatesSummary:
    """The mates stage's outcome for one assembly file.

    status: "ok" or "failed" (then ``error`` says why and the counts are zero).
    path: the written ``mates/<assembly>.parquet``. joint_types: suggested joint -> count.
    phase_seconds: wall time per phase of ``extract_mates`` (read, features, prune, ...).
    """

    assembly: str
    category: str
    source: str
    status: str
    error: str = ""
    seconds: float = 0.0
    path: str = ""
    n_parts: int = 0
    n_pairs: int = 0
    n_box_pairs: int = 0
    n_contact_pairs: int = 0
    face_mates: int = 0
    relations: int = 0
    joints: int = 0
    joint_types: dict[str, int] = field(default_factory=dict)
    phase_seconds: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class ScenesSummary:
    """The scenes stage's outcome: the table written, scenes in it, parts offered."""

    path: str
    scenes: int
    parts: int


@dataclass(frozen=True)
class CaptureSummary:
    """One capture (rendered from a scene, or read from a recording) and its learning inputs.

    error: empty when the capture and its inputs are fine, else the reason (the other counts
    say how far it got). seg_mean_iou: segmentation without ids scored against the ids (NaN
    when the capture has no ids). warnings: what the reader had to assume (a recording without
    a transform tree, colour left out), from ``RgbdFrame.meta["warnings"]``. input_parts: parts
    with learning inputs; scored: the part ids among them whose completion examples were
    built, to be scored from this capture (``cadio.capture.coverage``).
    """

    scene_id: str
    path: str
    frames: int = 0
    parts: int = 0
    bytes: int = 0
    input_parts: int = 0
    seg_mean_iou: float = math.nan
    error: str = ""
    warnings: tuple[str, ...] = ()
    scored: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class ExportSummary:
    """The export stage's outcome for one assembly.

    status: the sidecar's ("ok", "partial", "no-predictions") or "failed" (``reason`` says
    why; the sidecar is still written, with that status). The paths are those written, empty
    when not. pairs / predicted_pairs: pairs exported and those with a prediction;
    constraints: the mates the CadQuery script constrains (holds not counted).
    """

    assembly: str
    category: str
    status: str
    reason: str = ""
    sidecar: str = ""
    xbf: str = ""
    script: str = ""
    notes: int = 0
    pairs: int = 0
    predicted_pairs: int = 0
    constraints: int = 0
    relation_accuracy: float = math.nan
    joint_agreement: float = math.nan
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)
