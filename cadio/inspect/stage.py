"""The inspection stage: every assembly captured as built and checked against its design.

For each assembly of the night (its mates table written): the parts' CAD surfaces and
symmetries (``AssemblyModel``), the planted variants (``defects.plan_variants``), each captured
at real size by the inspection camera (``InspectConfig``: a D435 at 0.6 m, farther where the
assembly needs it to fit, a few views around it, and as many again nearer where asked) into
``captures/inspect-<assembly>-<variant>.mcap``: frames, cameras and instance ids only, never
the parts' names or poses, which go to ``inspect/<capture>.json`` for the scores alone. Each
capture is then inspected as a recording would be (``routes.by_design`` on all its views and
on one view alone), and the intact one also by ``routes.by_search`` (with a second ring of
views at 0.3 m that the intact capture holds for it alone), whose poses the relations of the
``registered`` input read. The results are plain records;
``cadio.inspect.evaluate`` turns them into rows.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cadio.camera.noise import D435
from cadio.camera.render import CaptureConfig, PlacedPart, render_views
from cadio.catalog import read_catalog
from cadio.inspect.asbuilt import Limits, MateAsBuilt, PartAsBuilt, assembly_as_built
from cadio.inspect.consensus import rest_in
from cadio.inspect.defects import DefectPlan, Variant, plan_variants
from cadio.inspect.routes import (
    AssemblyModel,
    Found,
    RouteConfig,
    alike_transforms,
    by_design,
    by_search,
    expected_points,
    onto_alike,
    shape_keys,
    visible_share,
)
from cadio.inspect.scan import Scan, scan_of
from cadio.inspect.surface import camera_of, part_surface
from cadio.inspect.symmetry import Symmetry, pose_error, symmetry_of
from cadio.recordings.foxglove_mcap import DEPTH_M, DEPTH_MM, CaptureWriter
from cadio.recordings.mcap_io import read_capture
from cadio.records import FloatArray
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.workspace import Workspace, atomic_write, read_mesh

log = logging.getLogger(__name__)

PREFIX = "inspect-"
ALL_VIEWS = "all"


@dataclass(frozen=True)
class InspectConfig:
    """Knobs of the inspection stage."""

    views: int = 4  # cameras around the assembly, a quarter turn apart
    distance_m: float = 0.6  # the D435's working range; farther where the assembly needs it
    # A second ring of ``views`` cameras this near (None: none), the robot moving the camera
    # in on the assembly's middle, all of which it need not frame: the sensor's noise falls
    # with the square of the distance (0.34 mm rms at 0.3 m against 1.4 mm at 0.6 m) and a
    # small part fills four times the pixels. The D435 measures from about 0.28 m. On the
    # held-out assemblies (all views, ``bench/studies/near_views.py``) the parts' pose error
    # is 0.11 mm at the median against 0.40 mm without it, shifts of 1, 2 and 5 mm are caught
    # 8 of 9, 8 of 8 and 8 of 8 times (5 of 9, 8 of 8, 6 of 8; sigmas of several views as
    # calibrated before the ring), no intact part flagged either way; the design route takes
    # 1.7 times as long (130 s against 75 s for the four).
    near_m: float | None = 0.3
    # The intact capture's near ring for the search route where ``near_m`` is None (None:
    # none), whose relations are scored against the CAD's mates.
    search_near_m: float | None = 0.3
    noise: bool = True  # the D435 model (``cadio.camera.noise.D435``)
    single_view: int | None = 0  # this view is also inspected alone (None: all views only)
    defects: DefectPlan = field(default_factory=DefectPlan)
    route: RouteConfig = field(default_factory=RouteConfig)
    search: bool = True  # the search route on the intact capture (the registered relations)
    tolerances: Tolerances = DEFAULT_TOLERANCES
    # The deviation image's tolerance: about twice the sensor's noise at 0.6 m (1.4 mm rms).
    deviation_mm: float = 3.0

    def camera(self, extent_mm: float) -> CaptureConfig:
        """The capture config: real size, the sensor model, and the distance, ``distance_m``
        or, where the assembly needs more, the nearest at which its bounding sphere (its box's
        diagonal across) fits the narrower field of view. Nearer is better: the sensor's noise
        grows with the square of the distance (an assembly 429 mm across fits at 0.66 m, 1.7 mm
        rms; framed with a margin at 0.89 m it was 3.0 mm, and its parts' poses several times
        worse)."""
        base = CaptureConfig(target_size_m=None, noise=D435 if self.noise else None)
        vfov = 2 * math.atan(math.tan(math.radians(base.hfov_deg) / 2) * base.height /
                             base.width)
        needed = extent_mm / 2 / 1000 / math.sin(vfov / 2)
        step = 360.0 / self.views
        return CaptureConfig(target_size_m=None, noise=base.noise,
                             distance_m=max(self.distance_m, needed), n_views=self.views,
                             step_deg=step)

    def rings(self, extent_mm: float, near_m: float | None) -> list[tuple[CaptureConfig, range]]:
        """The capture's cameras: the ring that frames the assembly (views 0 to ``views`` -
        1), then a near ring (``near_m``; None: none) at the same turns, its views numbered
        after them (so that its frames, stamps and noise draws are its own)."""
        far = self.camera(extent_mm)
        out = [(far, range(self.views))]
        if near_m:
            out.append((replace(far, distance_m=near_m), range(self.views, 2 * self.views)))
        return out

    def near_of(self, variant: str) -> float | None:
        """The near ring of a capture: ``near_m``, or the intact one's for the search."""
        if self.near_m:
            return self.near_m
        return self.search_near_m if self.search and variant == "intact" else None


def assembly_model(assembly: str, ws: Workspace) -> AssemblyModel:
    """The assembly's parts (by index, their meshes in the assembly frame) as registration
    reads them.

    Raises:
        ValueError: the catalog has no ok part of the assembly.
    """
    parts = tuple(part_surface(p, read_mesh(ws.mesh(p))) for p in part_ids(assembly, ws))
    symmetries = tuple(_symmetry(ws, p) for p in parts)
    shapes = shape_keys(parts, symmetries)
    return AssemblyModel(assembly, parts, tuple(np.eye(4) for _ in parts), symmetries, shapes,
                         alike_transforms(parts, shapes, lambda a, b: _onto(ws, a, b)))


def part_ids(assembly: str, ws: Workspace) -> list[str]:
    """The catalog's part ids of an assembly's solids, by index.

    Raises:
        ValueError: the catalog has no ok part of the assembly, or misses one.
    """
    catalog = read_catalog(ws.catalog)
    rows = catalog[(catalog["status"] == "ok") & (catalog["n_solids"] > 1)
                   & (catalog["source"].map(lambda s: Path(str(s)).stem) == assembly)]
    if rows.empty:
        raise ValueError(f"{assembly}: no part in the catalog")
    rows = rows.sort_values("solid_index")
    if list(rows["solid_index"]) != list(range(len(rows))):
        raise ValueError(f"{assembly}: parts {list(rows['solid_index'])} are not 0..n-1")
    return [str(p) for p in rows["part_id"]]


def _symmetry(ws: Workspace, part: Any) -> Symmetry:
    """The part's symmetry, kept in ``inspect/symmetries/<part_id>.json`` once found."""
    found = _kept(ws.root / "inspect" / "symmetries" / f"{part.part_id}.json",
                  lambda: symmetry_of(part.samples).to_dict())
    return Symmetry.from_dict(found)


def _onto(ws: Workspace, part: Any, other: Any) -> FloatArray:
    """The motion laying a part on another of its shape (``routes.onto_alike``: a search
    over turns, seconds a pair), kept in ``inspect/alike/<part_id>-<other_id>.json`` once
    found: part ids name their file's content and the solid."""
    found = _kept(ws.root / "inspect" / "alike" / f"{part.part_id}-{other.part_id}.json",
                  lambda: onto_alike(part, other).tolist())
    return np.array(found, dtype=np.float64)


def _kept(path: Path, make: Callable[[], Any]) -> Any:
    """The JSON value kept at ``path``; made by ``make`` and kept there the first time (read
    back as a later night reads it)."""
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path, "w") as fh:
            fh.write(json.dumps(make()))
    return json.loads(path.read_text())


def variants_of(model: AssemblyModel, mates: pd.DataFrame, cfg: InspectConfig) -> list[Variant]:
    """The intact assembly and its planted variants (parts the design shows enough of)."""
    if not any(cfg.defects.kinds()):
        return [Variant(model.name, "intact")]
    centres = [d[:3, :3] @ p.centre + d[:3, 3] for p, d in zip(model.parts, model.design,
                                                             strict=True)]
    cameras = _design_cameras(model, cfg)
    expected = expected_points(model, np.eye(4), Scan(np.zeros((0, 3)), np.zeros(0, np.int64),
                                                      cameras), cfg.route)
    eligible = [i for i, n in expected.items() if n >= cfg.route.missing_min_points]
    return plan_variants(model.name, mates, model.symmetries, centres, eligible, cfg.defects)


def _design_cameras(model: AssemblyModel, cfg: InspectConfig) -> tuple[Any, ...]:
    from cadio.camera.render import camera_intrinsics, camera_pose
    from cadio.inspect.surface import camera_of

    capture = cfg.camera(_extent(model))
    centre = _centre(model) / 1000
    return tuple(camera_of(camera_intrinsics(capture), camera_pose(capture, v, centre))
                 for v in range(cfg.views))


def _extent(model: AssemblyModel) -> float:
    lo, hi = _box(model)
    return float(np.linalg.norm(hi - lo))


def _centre(model: AssemblyModel) -> FloatArray:
    lo, hi = _box(model)
    centre: FloatArray = (lo + hi) / 2
    return centre


def _box(model: AssemblyModel) -> tuple[FloatArray, FloatArray]:
    verts = np.concatenate([p.mesh.vertices @ d[:3, :3].T + d[:3, 3]
                            for p, d in zip(model.parts, model.design, strict=True)])
    return verts.min(axis=0), verts.max(axis=0)


def capture_variant(model: AssemblyModel, variant: Variant, ws: Workspace,
                    cfg: InspectConfig) -> Path:
    """Render the variant as the inspection camera sees it into ``captures/<name>.mcap``
    (frames, cameras, instance ids; no scene description) and write what was planted and
    where every part stands to ``inspect/<name>.json``, for the scores alone."""
    name = capture_name(variant)
    poses = variant.poses(model.design, [p.centre for p in model.parts])
    path = record(model, poses, ws.capture(name), cfg, near_m=cfg.near_of(variant.name))
    truth = {"assembly": model.name, "variant": variant.name,
             "defects": [asdict(d) for d in variant.defects],
             "instances": {str(i + 1): i for i in sorted(poses)},
             "poses": {str(i): pose.tolist() for i, pose in poses.items()}}
    folder = ws.root / "inspect"
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_write(folder / f"{name}.json", "w") as fh:
        fh.write(json.dumps(truth))
    return path


def record(model: AssemblyModel, poses: dict[int, FloatArray], path: Path, cfg: InspectConfig,
           instance_ids: bool = True, near_m: float | None = None) -> Path:
    """Render the parts at ``poses`` (part -> assembly, mm) on a table, as the inspection
    camera sees them (and a near ring at ``near_m``), into an MCAP file: frames and cameras,
    and the renderer's instance ids where ``instance_ids`` (as a simulation's masks); never a
    scene description or a part's name. Without ids it is a recording as a RealSense driver
    writes one."""
    parts = [PlacedPart(instance_id=i + 1, mesh=model.parts[i].mesh, pose=pose,
                        colour="#b4b4b4", part_id=model.parts[i].part_id, label=str(i))
             for i, pose in sorted(poses.items())]
    # the sensor publishes millimetre steps (16UC1), as a D435's driver does; without the
    # sensor model the exact depth is written (32FC1 metres), or the steps would be its error
    with CaptureWriter(path, depth_encoding=DEPTH_MM if cfg.noise else DEPTH_M) as writer:
        for capture, views in cfg.rings(_extent(model), near_m):
            for frame in render_views(parts, capture, views):
                writer.write_frame(frame if instance_ids else replace(frame, instance=None))
    return path


def capture_name(variant: Variant) -> str:
    return f"{PREFIX}{variant.assembly}-{variant.name}"


@dataclass(frozen=True)
class Inspected:
    """One capture inspected with one set of its views (``views``: "all" or a view index).

    nominal: (4, 4) assembly -> world of the alignment; parts: each part as built (design
    route); mates: each face mate as built (design route), and as the ``design`` baseline
    (every part where the aligned design puts it); found: the search route's segments
    (intact captures); seconds: wall time per route.
    """

    capture: str
    views: str
    nominal: FloatArray
    parts: dict[int, PartAsBuilt]
    mates: list[MateAsBuilt]
    baseline: list[MateAsBuilt]
    found: list[Found] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    fits: dict[int, Any] = field(default_factory=dict)


def inspect_capture(model: AssemblyModel, path: Path, mates: pd.DataFrame, cfg: InspectConfig,
                    search: bool = False, fixture: FloatArray | None = None
                    ) -> list[Inspected]:
    """Inspect a capture as a recording: all its views together, and ``single_view`` alone;
    the search route too where ``search``. ``fixture``: where the cell holds the assembly
    (assembly -> world, mm), the design route's start; None: searched for."""
    import time

    frames = list(read_capture(path))
    whole = scan_of(frames)
    # (scan for the design route, scan for the search): a capture's near ring taken for the
    # search alone (``InspectConfig.search_near_m``) is not the design route's
    checked = whole if cfg.near_m or len(frames) <= cfg.views else \
        whole.of_views(list(range(cfg.views)))
    sets = [(ALL_VIEWS, checked, whole)]
    alone = cfg.single_view if cfg.single_view is not None and cfg.single_view < len(
        frames) else None
    # a capture of one view: that view alone is all of it, inspected once and said twice
    if alone is not None and len(frames) > 1:
        one = whole.of_views([alone])
        sets.append((str(alone), one, one))
    rows = mates.to_dict("records")
    limits = Limits.of(cfg.tolerances)
    out = []
    for views, scan, searched in sets:
        clock = time.perf_counter()
        nominal, parts, fits = by_design(model, scan, cfg.route, fixture)
        design_s = time.perf_counter() - clock
        designed = {i: nominal @ model.design[i] for i in range(len(model.parts))}
        # the baseline returns the design pose of every part it can see, and says nothing more
        baseline_parts = {i: PartAsBuilt(i, designed[i], parts[i].uncertainty,
                                         "" if parts[i].problem == "missing" else
                                         parts[i].problem) for i in parts}
        views_seen = len(scan.cameras)
        mates_built = assembly_as_built(rows, parts, dict(enumerate(model.design)), limits,
                                        rest_in(model, parts, nominal, views_seen))
        baseline = assembly_as_built(rows, baseline_parts, dict(enumerate(model.design)), limits,
                                     rest_in(model, baseline_parts, nominal, views_seen))
        found: list[Found] = []
        clock = time.perf_counter()
        if search and searched.segments:
            found = by_search(model, searched, cfg.route)
        out.append(Inspected(path.stem, views, nominal, parts, mates_built, baseline, found,
                             {"design": design_s, "search": time.perf_counter() - clock},
                             fits))
    if alone is not None and len(frames) == 1:
        out.append(replace(out[0], views=str(alone)))
    return out


def read_truth(ws: Workspace, capture: str) -> dict[str, Any]:
    """What was planted in a capture and where every part stood (the scores' only source)."""
    data: dict[str, Any] = json.loads((ws.root / "inspect" / f"{capture}.json").read_text())
    return data


def pose_rows(model: AssemblyModel, inspected: Inspected, truth: dict[str, Any]
              ) -> list[dict[str, Any]]:
    """Per registered part of a capture: its error against where it stood, least over its
    symmetries, with its visible share and fit. The ``design`` route's parts are known by
    index; a ``search`` segment is scored against the part that made it (its instance),
    its pose read as that part's where the search named another of the same shape, and
    whether it named it right (``named``)."""
    poses = {int(i): np.array(p) for i, p in truth["poses"].items()}
    made_by = {int(k): int(v) for k, v in truth["instances"].items()}
    found: list[tuple[str, int, FloatArray, bool]] = [
        ("design", i, p.pose, True) for i, p in sorted(inspected.parts.items())
        if p.pose is not None]
    for f in inspected.found:
        true = made_by.get(f.segment, f.index)
        found.append(("search", true, _read_as(model, f, true), true == f.index))
    rows = []
    for route, i, pose, named in found:
        if i not in poses:
            continue
        mm, deg = pose_error(pose, poses[i], model.symmetries[i])
        rows.append({"capture": inspected.capture, "views": inspected.views, "route": route,
                     "index": i, "part_id": model.parts[i].part_id,
                     "diameter_mm": model.parts[i].diameter, "error_mm": mm,
                     "error_deg": deg, "named": named})
    return rows


def scored_as(model: AssemblyModel, found: Sequence[Found], truth: dict[str, Any]
              ) -> dict[int, tuple[int, FloatArray]]:
    """Per search segment, the part its relations are scored as and its pose read as that
    part's. Copies of one shape look alike (which bolt of six, which ball of a ring, which of
    two flanges of a symmetric joint): where the segment's own part (the capture's instance
    masks) has the shape it was registered as, it is scored as that part, BOP's convention
    for interchangeable instances; the names ``name_parts`` gives are scored on their own
    (the poses' ``named``). A segment registered as another shape keeps its name (its pose is
    wrong either way), or takes a part of its shape no segment was scored as."""
    made_by = {int(k): int(v) for k, v in truth["instances"].items()}
    out: dict[int, tuple[int, FloatArray]] = {}
    taken: set[int] = set()
    others = []
    for f in found:
        true = made_by.get(f.segment, -1)
        if true >= 0 and model.shapes[true] == model.shapes[f.index]:
            out[f.segment] = (true, _read_as(model, f, true))
            taken.add(true)
        else:
            others.append(f)
    for f in others:
        free = [i for i, shape in enumerate(model.shapes)
                if shape == model.shapes[f.index] and i not in taken]
        if f.index not in taken or free:
            index = f.index if f.index not in taken else free[0]
            out[f.segment] = (index, _read_as(model, f, index))
            taken.add(index)
    return out


def _read_as(model: AssemblyModel, found: Found, index: int) -> FloatArray:
    """A search segment's pose read as part ``index``'s (a part of the shape it was named)."""
    as_first = found.fit.pose @ np.linalg.inv(model.alike[found.index]) if model.alike else \
        found.fit.pose
    return model.as_part(index, as_first)


def shares(model: AssemblyModel, path: Path, truth: dict[str, Any],
           views: Sequence[int] | None = None) -> dict[int, float]:
    """Per part, the share of its surface the capture's cameras (or ``views`` of them) see
    where it truly stands (the other parts hiding it). Only the cameras are read: what they
    see of a part is the other parts' doing, not the depth's."""
    cameras = [camera_of(f.intrinsics, f.world_to_camera) for f in read_capture(path)]
    if views is not None:
        cameras = [cameras[v] for v in views]
    poses = {int(i): np.array(p) for i, p in truth["poses"].items()}
    return visible_share(model, poses, cameras)
