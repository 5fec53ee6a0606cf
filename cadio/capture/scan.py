"""From scenes to captures and learning inputs: the capture stage of the nightly flow.

``capture_scene`` places a scene's parts (meshes from the workspace, poses from the scene
table), renders its views and writes one MCAP per scene with the ground-truth labels on
``/scene``; ``capture_batch`` does that for a batch of scene ids and derives their learning
inputs, and ``read_captures`` derives them from recordings made elsewhere. ``scan_inputs`` reads
any capture back and turns every part it shows into what the learned stages eat: the part's
completion examples in both protocols (``cadio.capture.examples``; the observed protocol's
inputs come from the observed points and the cameras alone) with the truth in the same grid for
the score, and 600 observed points in world metres. Parts are told apart by the instance ids; a
real recording without them is segmented by support-plane removal and clustering, scored against
the ids where both exist.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cadio.camera.noise import NoiseConfig
from cadio.camera.render import CaptureConfig, PlacedPart, render_views, scene_meta
from cadio.capture.examples import (
    OBSERVED,
    PROTOCOLS,
    Example,
    ExampleConfig,
    PartView,
    frame_supports,
    observed_example,
    oracle_example,
    part_views,
    view_input,
    view_sets,
    with_truth,
    write_example,
)
from cadio.capture.pointcloud import sample_points
from cadio.capture.segment import segment_clusters, segmentation_score
from cadio.catalog import read_catalog
from cadio.contracts import CaptureSummary
from cadio.errors import CaptureError, InputFileError, MachineError
from cadio.recordings.mcap_io import CaptureWriter, read_capture, read_scene_meta
from cadio.records import FloatArray, Mesh, Relation
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.relations import PairContact
from cadio.truth.scenes import read_scenes, scene_poses
from cadio.workspace import Workspace, atomic_write, read_mesh

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ScanConfig:
    """Knobs of the capture stage."""

    # Views rendered per scene, spread over the full circle (``view_indices``). No default
    # here: a night's comes from its configuration (``capture.views_per_scene``), one
    # capture's from its command.
    views_per_scene: int
    capture: CaptureConfig = field(default_factory=CaptureConfig)
    noise: bool = False
    # Completion examples of each part: every view on its own, and sequences of these lengths
    # (in both protocols), at the completion network's resolutions.
    n_in: int = 32
    n_out: int = 64
    lengths: tuple[int, ...] = (2, 4, 8)
    protocols: tuple[str, ...] = PROTOCOLS
    n_points: int = 600
    # ``grid_margin`` must equal the ingest's: the oracle-box grid is the part's truth grid.
    tolerances: Tolerances = DEFAULT_TOLERANCES

    def capture_config(self) -> CaptureConfig:
        return replace(self.capture, noise=NoiseConfig() if self.noise else None)

    def example_config(self) -> ExampleConfig:
        return ExampleConfig(n_in=self.n_in, n_out=self.n_out,
                             grid_margin=self.tolerances.grid_margin)


@dataclass(frozen=True)
class InputsSummary:
    """What ``scan_inputs`` made of one capture.

    parts: parts with learning inputs written; examples: completion examples written (of the
    ``scored`` parts only). has_ids: the capture has instance ids. clusters: clusters found
    without ids.
    seg_mean_iou, seg_ari: those clusters scored against the ids (NaN without ids).
    warnings: the reader's (``RgbdFrame.meta["warnings"]`` of the last frame).
    """

    capture: str
    frames: int
    parts: int
    has_ids: bool
    clusters: int
    examples: int = 0
    seg_mean_iou: float = math.nan
    seg_ari: float = math.nan
    warnings: tuple[str, ...] = ()
    scored: tuple[str, ...] = ()


def view_indices(cfg: ScanConfig) -> list[int]:
    """``views_per_scene`` view indices spread evenly over the camera circle."""
    total = cfg.capture.n_views
    k = min(cfg.views_per_scene, total)
    return sorted({round(i * total / k) % total for i in range(k)})


def placed_parts(scene: dict[str, Any], ws: Workspace, colours: dict[str, str]) -> list[PlacedPart]:
    """The two parts of a scene row, with meshes read from the workspace."""
    pose_a, pose_b = scene_poses(scene)
    return [
        PlacedPart(instance_id=i + 1, mesh=read_mesh(ws.mesh(pid)), pose=pose,
                   colour=colours.get(pid) or "#b4b4b4", part_id=pid, label=role)
        for i, (pid, pose, role) in enumerate(
            [(scene["part_a"], pose_a, "a"), (scene["part_b"], pose_b, "b")])
    ]


def scene_labels(scene: dict[str, Any]) -> dict[str, Any]:
    """Ground truth of a scene row: the ten relations of (a, b) seen along +Y (CAD frame) and
    what the pair's face mates say (``contact``: every view's labels need it)."""
    return {
        "view_axis": [0.0, 1.0, 0.0],
        "pair": [scene["part_a"], scene["part_b"]],
        "categories": [scene["category_a"], scene["category_b"]],
        "relations": {r.value: bool(scene[r.value]) for r in Relation},
        "contact": PairContact.from_dict(scene).to_dict(),
        "intended": scene.get("intended", ""),
        "split": scene.get("split", ""),
    }


def capture_scene(scene: dict[str, Any], ws: Workspace, colours: dict[str, str],
                  cfg: ScanConfig, on_frame: Callable[[str], None] | None = None
                  ) -> CaptureSummary:
    """Render a scene's views into ``captures/<scene_id>.mcap``.

    Returns:
        Path, frames, parts and bytes on disk (no inputs yet).
    """
    parts = placed_parts(scene, ws, colours)
    path = ws.capture(str(scene["scene_id"]))
    frames = write_views(path, parts, cfg, scene_labels(scene), on_frame)
    return CaptureSummary(scene_id=str(scene["scene_id"]), path=str(path), frames=frames,
                          parts=len(parts), bytes=path.stat().st_size)


def write_views(path: Path, parts: list[PlacedPart], cfg: ScanConfig,
                 labels: dict[str, Any], on_frame: Callable[[str], None] | None = None) -> int:
    """Render the views of ``cfg`` into one MCAP file; the number of frames written."""
    capture_cfg = cfg.capture_config()
    frames = 0
    with CaptureWriter(path) as writer:
        writer.write_scene(scene_meta(parts, capture_cfg, labels))
        for frame in render_views(parts, capture_cfg, view_indices(cfg)):
            writer.write_frame(frame)
            frames += 1
            if on_frame is not None:
                on_frame(str(path))
    return frames


def capture_scenes(scenes: pd.DataFrame, catalog: pd.DataFrame, ws: Workspace,
                   cfg: ScanConfig) -> list[CaptureSummary]:
    """Capture every scene row; a scene that fails becomes a summary with its error."""
    colours = dict(zip(catalog["part_id"], catalog["colour"], strict=True))
    out = []
    for scene in scenes.to_dict("records"):
        try:
            out.append(capture_scene(scene, ws, colours, cfg))
        except (OSError, ValueError, CaptureError) as exc:
            log.warning("scene %s: %s", scene["scene_id"], exc)
            out.append(CaptureSummary(scene_id=str(scene["scene_id"]), path="", error=str(exc)))
    return out


def capture_batch(scene_ids: list[str], ws: Workspace, cfg: ScanConfig,
                  plan: Mapping[str, Sequence[str]] | None = None) -> list[CaptureSummary]:
    """Render a batch of the workspace's scenes and derive their learning inputs.

    Args:
        plan: scene id -> the parts to score there (``cadio.capture.coverage.scoring_plan``;
            a scene it leaves out scores none); None: every part of every scene.
    """
    scenes = read_scenes(ws.scenes)
    scenes = scenes[scenes["scene_id"].isin(scene_ids)]
    captured = capture_scenes(scenes, read_catalog(ws.catalog), ws, cfg)
    return [c if c.error else with_inputs(
        c, ws, cfg, None if plan is None else plan.get(c.scene_id, ())) for c in captured]


ASSEMBLY_PREFIX = "assembly-"


def assembly_pairs(mates: pd.DataFrame) -> list[list[str]]:
    """Part pairs of an assembly's mates table: pairs with a face mate or a joint first, then
    those with part-level relations only, each in table order."""
    mated = mates[mates["level"] != "part"]
    ordered = [*zip(mated["part_a"], mated["part_b"], strict=True),
               *zip(mates["part_a"], mates["part_b"], strict=True)]
    return [list(p) for p in dict.fromkeys((str(a), str(b)) for a, b in ordered)]


def capture_assembly(assembly: str, category: str, part_ids: list[str], ws: Workspace,
                     cfg: ScanConfig, scored: Collection[str] | None = None) -> CaptureSummary:
    """Render an assembly (its parts as placed in the file) into
    ``captures/assembly-<name>.mcap`` and derive its inputs (learning examples of the
    ``scored`` parts, None: of all); the pairs its mates table names are the capture's
    labelled pairs. A failure comes back as the summary's error."""
    scene_id = f"{ASSEMBLY_PREFIX}{assembly}"
    try:
        mates = pd.read_parquet(ws.mates(assembly), columns=["part_a", "part_b", "level"])
        parts = [PlacedPart(instance_id=i + 1, mesh=read_mesh(ws.mesh(pid)), pose=np.eye(4),
                            colour="#b4b4b4", part_id=pid, label=pid)
                 for i, pid in enumerate(part_ids)]
        path = ws.capture(scene_id)
        labels = {"assembly": assembly, "category": category, "pairs": assembly_pairs(mates)}
        frames = write_views(path, parts, cfg, labels)
    except (OSError, ValueError, CaptureError) as exc:
        log.warning("assembly %s: %s", assembly, exc)
        return CaptureSummary(scene_id=scene_id, path="", error=str(exc))
    summary = CaptureSummary(scene_id=scene_id, path=str(path), frames=frames,
                             parts=len(parts), bytes=path.stat().st_size)
    return with_inputs(summary, ws, cfg, scored)


def read_captures(captures_dir: Path, ws: Workspace, cfg: ScanConfig,
                  skip: Collection[Path] = ()) -> list[CaptureSummary]:
    """Learning inputs of every recording made elsewhere (``*.mcap`` under the folder, in
    either MCAP dialect: ``cadio.recordings.mcap_io``), but those of ``skip`` (the
    recordings the inspection reads alone). A recording that cannot be used (no
    regular file: a folder or a pipe so named) gets its reason in the summary's ``error`` and
    the others go on. The reader refuses what it can tell is wrong (``read_capture``: sizes,
    intrinsics, poses, empty depth); whatever else a recording's content breaks in its scan is
    that recording's error too, named, and never the night's.

    Raises:
        MachineError: its inputs cannot be written into the workspace (the machine's fault).
    """
    out = []
    skipped = {Path(p).resolve() for p in skip}
    for path in sorted(Path(captures_dir).rglob("*.mcap")):
        if path.resolve() in skipped:
            continue
        summary = CaptureSummary(scene_id=path.stem, path=str(path))
        if not path.is_file():
            out.append(replace(summary, error="not a regular file (a folder or a pipe so "
                               "named): not read"))
            continue
        summary = replace(summary, bytes=path.stat().st_size)
        try:
            out.append(with_inputs(summary, ws, cfg))
        except MachineError:
            raise
        except Exception as exc:  # e.g. a camera looking straight down: this file's error
            log.warning("%s: %s: %s", path, type(exc).__name__, exc)
            out.append(replace(summary, error=f"{type(exc).__name__}: {exc}"))
    return out


def with_inputs(capture: CaptureSummary, ws: Workspace, cfg: ScanConfig,
                scored: Collection[str] | None = None) -> CaptureSummary:
    """The capture's summary after deriving its learning inputs (or with the reason it
    failed); ``scored`` as ``scan_inputs``."""
    try:
        inputs = scan_inputs(Path(capture.path), ws, cfg, scored)
    except CaptureError as exc:
        return replace(capture, error=exc.reason)
    except OSError as exc:
        return replace(capture, error=f"cannot be read: {exc.strerror or exc}")
    return replace(capture, frames=inputs.frames, input_parts=inputs.parts,
                   seg_mean_iou=inputs.seg_mean_iou, warnings=inputs.warnings,
                   scored=inputs.scored)


def scan_inputs(path: Path, ws: Workspace, cfg: ScanConfig,
                scored: Collection[str] | None = None) -> InputsSummary:
    """Learning inputs of every part of a capture, written to ``inputs/<capture>/<instance>/``.

    Parts are told apart by the instance ids (our captures) or, in a recording without them,
    by removing the support plane and clustering (scored against the ids when both exist).
    Every part seen in the scene meta gets 600 observed points of every view that sees it
    (world metres, for the relation network). A part the capture scores (its id in
    ``scored``; None: every part) gets its completion examples (``part_examples``); any other
    only the observed input of each single view (``examples.view_input``: what the relation
    stage completes), without the baselines, the sequences, the oracle-box protocol or the
    truth. Files of an earlier scan of the capture that this one does not write are removed.
    A recording without scene meta yields clusters but no part to score.

    Raises:
        CaptureError: the capture is corrupt before its first frame, has no frame, or shows
            parts the workspace does not know (a recording of another library).
    """
    meta = read_scene_meta(path) or {}
    frames = list(read_capture(path))
    if not frames:
        raise CaptureError(path, "no RGB-D frame in the capture")
    clusters = segment_clusters(frames[0])
    summary = InputsSummary(capture=str(path), frames=len(frames), parts=0,
                            has_ids=frames[0].instance is not None,
                            clusters=int(clusters.max()),
                            warnings=tuple(frames[-1].meta.get("warnings", ())))
    if frames[0].instance is not None:
        score = segmentation_score(clusters, frames[0].instance, frames[0].depth > 0)
        summary = replace(summary, seg_mean_iou=score.mean_iou, seg_ari=score.ari)
    if not meta.get("parts") or any(f.instance is None for f in frames):
        return summary
    unknown = [str(p["part_id"]) for p in meta["parts"] if not ws.mesh(str(p["part_id"])).is_file()]
    if unknown:
        raise CaptureError(path, f"shows parts that are not in the library's catalog ("
                           f"{', '.join(unknown[:5])}{' ...' if len(unknown) > 5 else ''}): "
                           "its parts cannot be scored")
    labels = [f.instance for f in frames if f.instance is not None]
    supports = frame_supports(frames, labels)  # one support plane a frame, for every part
    parts = examples = 0
    done: list[str] = []
    for part in meta["parts"]:
        pid, instance = str(part["part_id"]), int(part["instance_id"])
        views = part_views(frames, labels, instance, supports)
        if not views:
            continue
        scores = scored is None or pid in scored
        written = (part_examples(views, read_mesh(ws.mesh(pid)), part_to_world(meta, part), cfg)
                   if scores else view_inputs(views, cfg))
        # by instance: a scene may show a part twice
        _write_inputs(ws.inputs(path.stem, instance), written, views, cfg,
                      {"part_id": pid, "instance_id": instance, "capture": path.stem})
        parts += 1
        if scores:
            examples += len(written)
            done.append(pid)
    return replace(summary, parts=parts, examples=examples, scored=tuple(dict.fromkeys(done)))


def view_inputs(views: list[PartView], cfg: ScanConfig) -> dict[str, Example]:
    """The observed input of each single view of a part a capture does not score, by name
    (``observed-<view>``, as ``part_examples`` names the same view's example)."""
    ecfg = cfg.example_config()
    return {f"{OBSERVED}-{v.view}": view_input(v, ecfg) for v in views}


def _write_inputs(folder: Path, written: dict[str, Example], views: list[PartView],
                  cfg: ScanConfig, meta: dict[str, Any]) -> None:
    """One instance's examples and points into its input folder; stale ``.npz`` removed."""
    for name, example in written.items():
        write_example(folder / f"{name}.npz", example, meta)
    _write_points(folder / "points.npz", views, cfg)
    keep = {f"{name}.npz" for name in written} | {"points.npz"}
    for old in folder.glob("*.npz"):
        if old.name not in keep:
            old.unlink()


def part_to_world(meta: dict[str, Any], part: dict[str, Any]) -> FloatArray:
    """(4, 4) part mm -> world metres of a part of the scene meta: the truth side only."""
    scale = float(meta["scale_m_per_mm"])
    pose: FloatArray = np.diag([scale, scale, scale, 1.0]) @ np.asarray(part["pose_mm"],
                                                                        dtype=np.float64)
    return pose


def part_examples(views: list[PartView], mesh: Mesh, to_world: FloatArray,
                  cfg: ScanConfig) -> dict[str, Example]:
    """A part's examples, by name (``<protocol>-<views>``): each view alone and the
    sequences of ``cfg.lengths`` views, in each protocol, with targets for the score.

    The observed protocol's inputs come from the views alone; ``mesh`` and ``to_world`` (the
    truth) place the oracle-box grid and voxelize the targets.
    """
    ecfg = cfg.example_config()
    out = {}
    for chosen in view_sets(len(views), len(views), cfg.lengths):
        seq = [views[i] for i in chosen]
        for protocol in cfg.protocols:
            example = (observed_example(seq, ecfg) if protocol == OBSERVED
                       else oracle_example(seq, mesh, to_world, ecfg))
            name = f"{protocol}-{'-'.join(str(v.view) for v in seq)}"
            out[name] = with_truth(example, mesh, to_world, ecfg)
    return out


def _write_points(path: Path, views: list[PartView], cfg: ScanConfig) -> None:
    """Every view's ``n_points`` observed points of a part (the relation stage's input):
    points (V, k, 3) float32 world metres, view (V,) indices, world_to_camera (V, 4, 4) and
    observed (V,) counts before sampling."""
    with atomic_write(path) as fh:
        np.savez_compressed(
            fh, points=np.stack([sample_points(v.points, cfg.n_points) for v in views]
                                ).astype(np.float32),
            view=np.array([v.view for v in views], dtype=np.int64),
            world_to_camera=np.stack([v.evidence.world_to_camera for v in views]),
            observed=np.array([len(v.points) for v in views], dtype=np.int64))


def capture_step(target: str, workspace: Path, cfg: ScanConfig,
                 on_frame: Callable[[str], None] | None = None) -> CaptureSummary:
    """Capture a STEP file (all its solids, as placed in the file) or a scene id of the table.

    Args:
        on_frame: called once per frame written (for progress bars).

    Raises:
        InputFileError: ``target`` is neither a readable STEP file nor a known scene id.
    """
    ws = Workspace(Path(workspace))
    path = Path(target)
    if path.is_file():
        return _capture_file(path, ws, cfg, on_frame)
    if ws.scenes.exists():
        scenes = read_scenes(ws.scenes)
        match = scenes[scenes["scene_id"].astype(str) == str(target)]
        if len(match):
            catalog = read_catalog(ws.catalog)
            colours = dict(zip(catalog["part_id"], catalog["colour"], strict=True))
            return capture_scene(match.iloc[0].to_dict(), ws, colours, cfg, on_frame)
    raise InputFileError(target, "neither a STEP file nor a scene id of the workspace")


def _capture_file(path: Path, ws: Workspace, cfg: ScanConfig,
                  on_frame: Callable[[str], None] | None) -> CaptureSummary:
    from cadio.cad.ingest import file_sha256, part_id
    from cadio.cad.step import read_step
    from cadio.cad.tessellate import tessellate

    # the ids ingest gives the file's solids: a night reading this recording scores them
    sha = file_sha256(path)
    parts = [PlacedPart(instance_id=s.info.index + 1, mesh=tessellate(s.shape, cfg.tolerances),
                        pose=np.eye(4), colour=s.info.colour or "#b4b4b4",
                        part_id=part_id(sha, s.info.index), label=s.info.name)
             for s in read_step(path)]
    out = ws.capture(path.stem)
    frames = write_views(out, parts, cfg, {"source": str(path)}, on_frame)
    return CaptureSummary(scene_id=path.stem, path=str(out), frames=frames, parts=len(parts),
                          bytes=out.stat().st_size)
