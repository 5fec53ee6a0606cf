"""Learning examples for shape completion: the inputs a camera gives, the truth in the same grid.

One example is one part seen in a sequence of V >= 1 views, in one cube (``observe.CubeGrid``):

- ``inputs`` (V, 2, n_in^3) bool, each view's seen-surface and seen-free voxels (a voxel in
  neither is unknown: ``observe.view_states``); ``depth`` (V, 2, 2 n_in, 2 n_in) float32, each
  view's seen surface as a depth image along the cube's +y (``observe.depth_view``);
- the two baselines that need no learning, at the output resolution: ``visible`` (the views'
  seen surface) and ``carve`` (``observe.carve``);
- ``target`` (n_out^3) bool, the part's solid in the cube, for the loss and the score only.

``observed_example`` builds the inputs of the observed protocol from the views alone (its
signature takes nothing else, and a test checks that nothing of the truth changes it);
``oracle_example`` builds the oracle-box comparison in the part's truth grid; ``with_truth``
adds the target. ``render_part_views`` renders one part on its own from the paper's camera
circle, as the training set needs; ``part_views`` cuts a part's views out of any capture.
Examples are written one per ``.npz`` file (keys as above plus ``meta``, a JSON string).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from cadio.camera.render import CaptureConfig, PlacedPart, render_views
from cadio.capture.observe import (
    SURFACE,
    CubeGrid,
    GridRule,
    PartGrids,
    ViewEvidence,
    camera_azimuth_deg,
    depth_view,
    occluded_sides,
    oracle_grid,
    place_grid,
    states_and_carve,
    truth_occupancy,
    union_states,
    view_states,
)
from cadio.capture.pointcloud import backproject
from cadio.capture.segment import SegmentConfig, fit_plane
from cadio.records import FloatArray, Mesh, RgbdFrame
from cadio.workspace import atomic_write

OBSERVED, ORACLE = "observed", "oracle-box"
PROTOCOLS = (OBSERVED, ORACLE)
# Fewer observed points than this and a view says too little to place a grid on.
MIN_POINTS = 30
# Observed points kept with an example, for registering the completion onto the scan.
POINTS_KEPT = 2048
# The support plane is fitted to every this-many-th pixel of no part: a table is hundreds of
# thousands of returns, and a plane needs far fewer.
SUPPORT_STRIDE = 8


@dataclass(frozen=True)
class ExampleConfig:
    """Resolutions and the grid rule. CPU default 32^3 in, 64^3 out; the paper 64 -> 256."""

    n_in: int = 32
    n_out: int = 64
    rule: GridRule = field(default_factory=GridRule)
    grid_margin: float = 0.05  # the oracle-box grid's margin: ``Tolerances.grid_margin``

    @property
    def d(self) -> int:
        """Side of the 2D depth image: twice the input grid, as R2N2 sees finer than voxels."""
        return 2 * self.n_in


@dataclass(frozen=True)
class PartView:
    """One view of one part: its observed points (m, 3) in world metres and the evidence."""

    view: int
    azimuth_deg: float
    points: FloatArray
    evidence: ViewEvidence


@dataclass(frozen=True, eq=False)
class Example:
    """One part in a sequence of views, in one cube (see the module docstring for shapes)."""

    protocol: str
    views: tuple[int, ...]
    azimuths: tuple[float, ...]
    grid: CubeGrid
    inputs: npt.NDArray[np.bool_]
    depth: npt.NDArray[np.float32]
    visible: npt.NDArray[np.bool_]
    carve: npt.NDArray[np.bool_]
    points: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))  # observed, world m
    target: npt.NDArray[np.bool_] | None = None
    coverage: float = math.nan  # share of the part's volume inside the cube
    voxel_mm: float = math.nan  # an output voxel's edge in the part's millimetres (scoring)
    meta: dict[str, Any] = field(default_factory=dict)


def part_views(frames: Sequence[RgbdFrame], labels: Sequence[npt.NDArray[np.int32]],
               label: int,
               supports: Sequence[tuple[FloatArray, float] | None] | None = None
               ) -> list[PartView]:
    """The views of the part whose pixels carry ``label`` (instance ids or clusters), each
    frame's labels given in ``labels``; views where it shows fewer than ``MIN_POINTS`` points
    are left out. A view is known by its index on the camera circle where the frame says so
    (rendered frames), else by its order in the capture; its azimuth comes from the camera.
    ``supports``: each frame's ``support_plane``, where the caller has them (a frame showing
    several parts needs it once)."""
    out = []
    for order, (frame, lab) in enumerate(zip(frames, labels, strict=True)):
        mask = lab == label
        points = backproject(frame, mask)
        if len(points) < MIN_POINTS:
            continue
        support = supports[order] if supports is not None else support_plane(frame, lab)
        evidence = ViewEvidence(frame.depth, mask, frame.intrinsics, frame.world_to_camera,
                                support, others=(lab > 0) & ~mask)
        view = int(frame.meta.get("view_index", order))
        out.append(PartView(view, camera_azimuth_deg(frame.world_to_camera), points, evidence))
    return out


def frame_supports(frames: Sequence[RgbdFrame], labels: Sequence[npt.NDArray[np.int32]]
                   ) -> list[tuple[FloatArray, float] | None]:
    """Each frame's ``support_plane``, for ``part_views`` of every part of a capture."""
    return [support_plane(f, lab) for f, lab in zip(frames, labels, strict=True)]


def support_plane(frame: RgbdFrame,
                  labels: npt.NDArray[np.int32]) -> tuple[FloatArray, float] | None:
    """The support plane under the parts (normal up, offset), fitted to the pixels of no part
    (label 0: table and background returns), or None when too few of them have depth."""
    rest = backproject(frame, labels == 0, SUPPORT_STRIDE)
    if len(rest) < 100:
        return None
    normal, offset = fit_plane(rest, SegmentConfig())
    if normal[2] < 0:
        normal, offset = -normal, -offset
    return normal, offset


def observed_example(views: Sequence[PartView], cfg: ExampleConfig) -> Example:
    """The observed protocol: the cube placed from the views' points and the first camera.

    Raises:
        ValueError: no view.
    """
    if not views:
        raise ValueError("an example needs at least one view")
    points = np.concatenate([v.points for v in views])
    first = views[0].evidence
    grid = place_grid(points, first.world_to_camera, cfg.rule,
                      occluded_sides(first, cfg.rule), first.support)
    return _inputs(OBSERVED, views, grid, cfg)


def view_input(view: PartView, cfg: ExampleConfig) -> Example:
    """The observed protocol's input of one view and nothing more: the grid, the view's voxel
    states and points as ``observed_example`` of that view has them, without the baselines
    (``depth``, ``visible`` and ``carve`` are empty) or a target. What the relation stage
    completes of a part in a capture that does not score it."""
    first = view.evidence
    grid = place_grid(view.points, first.world_to_camera, cfg.rule,
                      occluded_sides(first, cfg.rule), first.support)
    empty = np.zeros((0,), dtype=bool)
    return Example(
        protocol=OBSERVED, views=(view.view,), azimuths=(view.azimuth_deg,), grid=grid,
        inputs=view_states(first, view.points, grid, cfg.n_in)[None],
        depth=np.zeros((0,), dtype=np.float32), visible=empty, carve=empty,
        points=_sample(view.points, POINTS_KEPT), meta={"input_only": True})


def oracle_example(views: Sequence[PartView], mesh: Mesh, part_to_world: FloatArray,
                   cfg: ExampleConfig, grids: PartGrids | None = None) -> Example:
    """The oracle-box protocol (the paper's setting): the part's truth grid, true pose."""
    if not views:
        raise ValueError("an example needs at least one view")
    grid = (grids.oracle(mesh, part_to_world, cfg.grid_margin) if grids is not None
            else oracle_grid(mesh, part_to_world, cfg.grid_margin))
    return _inputs(ORACLE, views, grid, cfg, grids)


def _inputs(protocol: str, views: Sequence[PartView], grid: CubeGrid,
            cfg: ExampleConfig, grids: PartGrids | None = None) -> Example:
    points = np.concatenate([v.points for v in views])
    out, carved = states_and_carve([v.evidence for v in views], [v.points for v in views],
                                   grid, cfg.n_out, grids)
    fine = out if cfg.n_out == cfg.d else [
        view_states(v.evidence, v.points, grid, cfg.d, grids) for v in views]
    return Example(
        protocol=protocol, views=tuple(v.view for v in views),
        azimuths=tuple(v.azimuth_deg for v in views), grid=grid,
        inputs=np.stack([view_states(v.evidence, v.points, grid, cfg.n_in, grids)
                         for v in views]),
        depth=np.stack([depth_view(f[SURFACE]) for f in fine]),
        visible=union_states(np.stack(out))[SURFACE], carve=carved,
        points=_sample(points, POINTS_KEPT))


def _sample(points: FloatArray, k: int) -> FloatArray:
    """At most k of the points, a seeded random choice (the registration's scan side)."""
    if len(points) <= k:
        return points
    keep = np.random.default_rng(0).choice(len(points), k, replace=False)
    return points[np.sort(keep)]


def with_truth(example: Example, mesh: Mesh, part_to_world: FloatArray,
               cfg: ExampleConfig, grids: PartGrids | None = None) -> Example:
    """The example with its target (the solid in the cube) and the share of the part's
    volume the cube holds (a cube placed from a view can cut a part the view barely saw)."""
    target = (grids.truth(mesh, part_to_world, example.grid, cfg.n_out) if grids is not None
              else truth_occupancy(mesh, part_to_world, example.grid, cfg.n_out))
    scale = float(np.cbrt(abs(np.linalg.det(np.asarray(part_to_world)[:3, :3]))))
    volume_m3 = _mesh_volume(mesh) * scale**3
    inside_m3 = float(target.sum()) * example.grid.voxel_m(cfg.n_out) ** 3
    coverage = min(1.0, inside_m3 / volume_m3) if volume_m3 > 0 else math.nan
    return replace(example, target=target, coverage=coverage,
                   voxel_mm=example.grid.voxel_m(cfg.n_out) / scale)


def _mesh_volume(mesh: Mesh) -> float:
    v = mesh.vertices[mesh.triangles]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


# ---------------------------------------------------------------- one part on its own


def part_pose(part_id: str, mesh: Mesh) -> FloatArray:
    """A seeded pose for rendering a part alone: a turn about Z, and lying on its side for
    about a third of the parts, so the views do not all see parts as modelled."""
    seed = int(hashlib.sha256(part_id.encode()).hexdigest()[:8], 16)
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(0, 2 * math.pi)
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    if rng.random() < 1 / 3:
        rot = rot @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = -rot @ (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0)) / 2
    return pose


def render_part_views(mesh: Mesh, pose: FloatArray, views: Sequence[int],
                      capture: CaptureConfig) -> tuple[list[PartView], FloatArray]:
    """Render a part alone on the support plane from the given views of the camera circle.

    Returns:
        The part's views (those that see enough of it) and its part-to-world map (4, 4),
        part mm -> world metres (the truth side only needs it).
    """
    part = PlacedPart(instance_id=1, mesh=mesh, pose=pose, part_id="part")
    frames = list(render_views([part], capture, views))
    scale = float(frames[0].meta["scale_m_per_mm"]) if frames else 1e-3
    labels = [f.instance if f.instance is not None else np.zeros_like(f.depth, dtype=np.int32)
              for f in frames]
    part_to_world = np.diag([scale, scale, scale, 1.0]) @ pose
    return part_views(frames, labels, 1), part_to_world


def view_sets(n_views: int, singles: int, lengths: Sequence[int]) -> list[tuple[int, ...]]:
    """Which of a part's ``n_views`` rendered views make examples: ``singles`` single views
    spread over the circle, then sequences of each length starting at view 0, views spread."""
    sets: list[tuple[int, ...]] = [(round(i * n_views / singles),) for i in range(singles)]
    for length in lengths:
        if 1 < length <= n_views:
            sets.append(tuple(round(i * n_views / length) for i in range(length)))
    return sets


# ---------------------------------------------------------------- files


def write_example(path: Path, example: Example, meta: dict[str, Any]) -> None:
    """One example as a compressed ``.npz`` (atomic); ``meta`` joins the example's own."""
    g = example.grid
    info = {**meta, **example.meta, "protocol": example.protocol, "views": list(example.views),
            "azimuths": list(example.azimuths), "coverage": example.coverage,
            "voxel_mm": example.voxel_mm,
            "grid": {"rotation": g.rotation.tolist(), "corner": g.corner.tolist(),
                     "side": g.side}}
    arrays: dict[str, Any] = {"inputs": example.inputs, "depth": example.depth.astype(np.float16),
                              "visible": example.visible, "carve": example.carve,
                              "points": example.points.astype(np.float32),
                              "meta": np.array(json.dumps(info))}
    if example.target is not None:
        arrays["target"] = example.target
    with atomic_write(path) as fh:
        np.savez_compressed(fh, **arrays)


def read_example(path: Path) -> Example:
    """An example written by ``write_example``."""
    with np.load(path) as z:
        info = json.loads(str(z["meta"]))
        g = info["grid"]
        return Example(
            protocol=info["protocol"], views=tuple(info["views"]),
            azimuths=tuple(info["azimuths"]),
            grid=CubeGrid(np.array(g["rotation"]), np.array(g["corner"]), float(g["side"])),
            inputs=z["inputs"], depth=z["depth"].astype(np.float32), visible=z["visible"],
            carve=z["carve"], points=z["points"].astype(np.float64),
            target=z["target"] if "target" in z else None,
            coverage=_float(info.get("coverage")), voxel_mm=_float(info.get("voxel_mm")),
            meta=info)


def _float(value: Any) -> float:
    return math.nan if value is None else float(value)
