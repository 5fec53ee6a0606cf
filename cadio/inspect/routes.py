"""The two routes from a scan to the parts' poses.

``by_design`` (inspection software's way, for the as-built check): align the whole assembly as
designed to the scan (one rigid body, found without its pose: ``register.global_search``), then
refine each part locally from its place in it, larger parts first; the points a placed part
explains are not offered to the next. A part whose designed place the cameras should see but
the scan does not fill is missing; one the design itself hides is not inspectable.

``by_search`` (for the relations read from the registered B-reps, where the design must not
reach the answer): each segment of the scan is registered to each part shape of the bill of
materials that could be it, without any prior pose, and given to the best; parts of one shape
are told apart by where the segments lie together (``name_parts``: a name, never a pose).

Everything is millimetres, world frame; a part is known by its index in the assembly.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt
from scipy.optimize import linear_sum_assignment

from cadio.inspect.asbuilt import PartAsBuilt
from cadio.inspect.register import (
    Fit,
    RegisterConfig,
    global_search,
    refine,
    seen_tree,
    settled,
)
from cadio.inspect.scan import Scan, consistency
from cadio.inspect.surface import Camera, Occluders, PartSurface, occluders, visible
from cadio.inspect.symmetry import Symmetry
from cadio.inspect.uncertainty import PoseUncertainty, pose_uncertainty
from cadio.records import FloatArray, Mesh, apply_pose


@dataclass(frozen=True, eq=False)
class AssemblyModel:
    """An assembly as designed: its parts' surfaces, designed poses (part -> assembly, mm),
    symmetries and shapes (parts of one shape key are interchangeable to a camera)."""

    def as_part(self, index: int, pose: FloatArray) -> FloatArray:
        """A pose of the first part of ``index``'s shape read as ``index``'s own pose."""
        if not self.alike:
            return pose
        out: FloatArray = pose @ self.alike[index]
        return out

    name: str
    parts: tuple[PartSurface, ...]
    design: tuple[FloatArray, ...]
    symmetries: tuple[Symmetry, ...]
    shapes: tuple[str, ...]
    # per part, its frame -> the frame of the first part of its shape (the search registers
    # that one's surface; the others' poses follow): identity for the first
    alike: tuple[FloatArray, ...] = ()
    _whole: list[PartSurface] = field(default_factory=list, repr=False)

    def whole(self) -> PartSurface:
        """The assembly as one rigid body, as designed (for the nominal alignment)."""
        if not self._whole:
            from cadio.inspect.surface import part_surface

            meshes = [Mesh(apply_pose(d, p.mesh.vertices), p.mesh.triangles)
                      for p, d in zip(self.parts, self.design, strict=True)]
            offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
            merged = Mesh(np.concatenate([m.vertices for m in meshes]),
                          np.concatenate([m.triangles + o for m, o in zip(meshes, offsets,
                                                                        strict=True)]))
            self._whole.append(part_surface(self.name, merged, samples=40_000))
        return self._whole[0]


@dataclass(frozen=True)
class RouteConfig:
    """Knobs of the two routes."""

    register: RegisterConfig = field(default_factory=RegisterConfig)
    # From its place in the aligned design a part is a few millimetres off at most: it is
    # refined at the fine distance only (a coarse one lets a neighbour's points pull it), each
    # step kept only where it fits the points better (``register._icp``).
    local: RegisterConfig = field(default_factory=lambda: RegisterConfig(
        scales=(), iterations=30, monotone=True))
    # A part the design shows fewer scan-sized points of than this is not inspectable; one it
    # shows but the scan covers less than ``missing_coverage`` of, after its refinement, is
    # missing, unless the depth agrees with ``found_above`` of its designed place (it stands
    # there, and its fit went astray: not inspectable).
    min_visible: int = 60
    missing_coverage: float = 0.15
    # A part is called missing only where the design shows this many of its points: of one
    # it barely shows, too few scan points are no evidence either way (not inspectable).
    missing_min_points: int = 240
    # A part whose designed place the depth contradicts on more than half of what the cameras
    # would see of it (they saw farther: free space) is not there; it is missing unless its
    # refinement found it where the depth agrees on ``found_above`` of it and covers
    # ``found_coverage`` (a part moved: its mates judge it). On five real assemblies no intact
    # part was seen through on more than 30% of its place, a missing one on 48% to 100%.
    absent_below: float = 0.5
    found_above: float = 0.9
    found_coverage: float = 0.5
    # ...and it is missing however few points the design shows of it (``min_visible`` at
    # least) where the depth agrees with less than this of its place: seen through on three
    # quarters of 60 points or more is evidence. On the held-out night's captures (four
    # assemblies, seven variants, all views and one) no part left in place agreed with less
    # than 0.67 of its place, none shifted or turned with less than 0.33, and two studs
    # missing from one view of the flange with 0.04 and 0.07 of theirs (80-88 points: they
    # were "too little of it seen").
    absent_sure: float = 0.25
    # A segment is registered to a shape only where the shape's diameter allows its extent;
    # the shapes are tried smallest first, and a fit this good (inlier share of the segment,
    # share of its visible CAD the depth does not contradict) ends the search. Where the scan
    # is segmented, the second share is of the visible CAD neither the depth nor another
    # segment contradicts (``scan.consistency``), and ``good_owned`` takes its place: a part
    # pressed against others loses some of its rim to them (on the held-out flange a washer
    # under its nut keeps 0.88 of its surface, a stud's end beside its nut 0.96, and a nut's
    # shape laid over that end and onto the nut beside it 0.54-0.70).
    extent_slack_mm: float = 3.0
    good_fit: tuple[float, float] = (0.9, 0.9)
    good_owned: float = 0.8
    many_times: float = 3.0
    # ...except that a segment smaller than ``alike_below_mm`` is tried on every shape up to
    # ``alike_window`` times its extent first: a nut and a bolt's end, a ball and a roller of
    # one size all fit a small segment well, and the first is not the likeliest.
    alike_window: float = 1.5
    alike_below_mm: float = 40.0
    correlated_points: float = 16.0  # ``uncertainty.pose_uncertainty``
    # The sigma of a fit to several views is widened by this: each view's correlated errors
    # (and its camera's pose) stay whole however many points it gives, so the views need not
    # average like independent points. Calibrated on development assemblies, intact, with the
    # D435 model (``bench/studies/pose_sigma.py``): with the old ICP (steps composed out of
    # order, none checked) and no near ring, a mate's residual over its sigma had a median of
    # 1.32 (all views) against 0.67 for a normal error, and 1.3 was set; with the checked
    # steps and the near ring (OCCT as1, a handwheel, a pillow block, the AeroAssembly; 300
    # residuals) it reads 0.42 at the median and 1.45 at the 95th percentile (normal 1.96)
    # with 1.3: the tails, which the three-sigma thresholds meet, match a normal error at 1.0.
    # With each point weighed by its depth's inverse variance (``RegisterConfig.weighted``)
    # the residuals read smaller against their sigmas (the same 300: 0.43 at the median and
    # 1.66 at the 95th percentile with 1.0): 0.85.
    several_views_sigma: float = 0.85


def by_design(model: AssemblyModel, scan: Scan, cfg: RouteConfig = RouteConfig(),
              fixture: FloatArray | None = None
              ) -> tuple[FloatArray, dict[int, PartAsBuilt], dict[int, Fit]]:
    """The nominal alignment (assembly -> world) and each part as built, from the design.

    With a ``fixture`` (where the cell holds the assembly, assembly -> world), the whole
    assembly is fitted from there, as inspection software aligns to nominal. Without one it
    is searched for; a whole that is nearly symmetric (a plate's bolts on a square) then
    leaves several nominals, and of its best fits and their turns by its symmetries, the one
    whose parts, refined, explain the scan best is taken (on a symmetric whole the answer
    may be its symmetric copy: the mates are the same, their parts' names swapped).

    Raises:
        ValueError: the scan has too few points to align the assembly to.
    """
    if fixture is not None:
        whole = refine(model.whole(), scan.points, fixture, scan.cameras,
                       replace(cfg.register, stride=max(2, cfg.register.stride)),
                       sigma=scan.sigma)
        placed, fits, _ = _place_parts(model, scan, whole.pose, cfg)
        return whole.pose, placed, fits
    best: tuple[tuple[float, float], FloatArray, dict[int, PartAsBuilt],
                dict[int, Fit]] | None = None
    for nominal in nominal_candidates(model, scan, cfg):
        placed, fits, explained = _place_parts(model, scan, nominal, cfg)
        score = (round(explained / max(len(scan.points), 1), 1), -settled(_rms(fits)))
        if best is None or score > best[0]:
            best = (score, nominal, placed, fits)
    assert best is not None
    return best[1], best[2], best[3]


def _rms(fits: Mapping[int, Fit]) -> float:
    """The parts' point-to-plane RMS together (each weighted by its inliers)."""
    total = sum(f.inliers for f in fits.values() if np.isfinite(f.rmse_mm))
    if not total:
        return float("inf")
    return float(np.sqrt(sum(f.inliers * f.rmse_mm ** 2 for f in fits.values()
                             if np.isfinite(f.rmse_mm)) / total))


def _place_parts(model: AssemblyModel, scan: Scan, nominal: FloatArray, cfg: RouteConfig
                 ) -> tuple[dict[int, PartAsBuilt], dict[int, Fit], int]:
    """Each part refined from its place in the nominal, larger parts first, and how many of
    the scan's points they explain together."""
    placed: dict[int, PartAsBuilt] = {}
    fits: dict[int, Fit] = {}
    used = np.zeros(len(scan.points), dtype=bool)
    expected = expected_points(model, nominal, scan, cfg)
    others = occluders([(i, p.mesh, nominal @ d) for i, (p, d) in
                        enumerate(zip(model.parts, model.design, strict=True))])
    label = designed_labels(others, scan)
    for i in sorted(range(len(model.parts)), key=lambda k: -model.parts[k].diameter):
        part, start = model.parts[i], nominal @ model.design[i]
        if expected[i] < cfg.min_visible:
            placed[i] = PartAsBuilt(i, None, None, "too little of it visible")
            continue
        # the points the design shows of this part, or of none (where a part moved off its
        # place shows): never a neighbour's, whose faces touch this one's
        mine = ~used & ((label == i) | (label < 0))
        offered = scan.points[mine]
        here = _agreement(part, start, scan, cfg, (others, i))
        if len(offered) < 6:
            # no points where the design shows it: gone where the design shows enough of it
            # or the depth sees through its place; else too little seen (a ball between its
            # neighbours shows a rim that the sensor drops at the edges)
            placed[i] = PartAsBuilt(i, None, None, "missing" if expected[i] >=
                                    cfg.missing_min_points or here < cfg.absent_sure
                                    else "too little of it seen")
            continue
        fit = refine(part, offered, start, scan.cameras, cfg.local, (others, i),
                     sigma=scan.sigma_of(mine))
        fits[i] = fit
        if here < cfg.absent_below and not (
                fit.coverage >= cfg.found_coverage
                and _agreement(part, fit.pose, scan, cfg, (others, i)) >= cfg.found_above):
            # the camera sees through where the design puts it, and the refinement found it
            # nowhere the depth agrees with: gone (refined from an empty place, a part slides
            # onto what lies behind it, a nut onto its washer)
            placed[i] = PartAsBuilt(i, None, None, "missing" if expected[i] >=
                                    cfg.missing_min_points or here < cfg.absent_sure
                                    else "too little of it seen")
            continue
        if fit.coverage < cfg.missing_coverage:
            # the refinement covers too little of it: gone, unless the depth agrees with its
            # designed place (a fit pulled off a part that stands there is no evidence it is
            # gone: a pillow block's bearing seen from one view was called missing there)
            placed[i] = PartAsBuilt(i, None, None, "missing" if expected[i] >=
                                    cfg.missing_min_points and here < cfg.found_above
                                    else "too little of it seen")
            continue
        placed[i] = PartAsBuilt(i, fit.pose, _uncertainty(part, fit, cfg,
                                                          len(scan.cameras)))
        # a part explains only points it was offered: a washer's rim under its nut lies
        # within the fine distance of the nut, and is the washer's
        seen = fit.seen if cfg.local.stride == cfg.register.stride else None
        used |= _explained(part, fit.pose, scan, cfg, (others, i), seen) & \
            ((label == i) | (label < 0))
    return placed, fits, int(used.sum())


def designed_labels(design: Occluders, scan: Scan) -> npt.NDArray[np.int64]:
    """(n,) per scan point, the part the design (placed in the world) shows at its pixel:
    the first it meets on the ray from the point's camera through it (-1: none)."""
    label = np.full(len(scan.points), -1, dtype=np.int64)
    for v, camera in enumerate(scan.cameras):
        mine = np.flatnonzero(scan.view == v)
        if not len(mine):
            continue
        dirs = scan.points[mine] - camera.centre
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        rays = np.hstack([np.broadcast_to(camera.centre, dirs.shape), dirs]).astype(np.float32)
        label[mine] = design.first(rays)[1]
    return label


def nominal_candidates(model: AssemblyModel, scan: Scan, cfg: RouteConfig) -> list[FloatArray]:
    """Poses of the whole assembly (assembly -> world) found without any prior pose: its best
    fits, and the best turned by each near-symmetry of the whole (a 2 mm tolerance: a whole
    that is symmetric but for its small parts)."""
    from cadio.inspect.symmetry import symmetry_of

    whole = model.whole()
    fits = global_search(whole, scan.points, scan.cameras,
                         replace(cfg.register, stride=max(2, cfg.register.stride), keep=2))
    turns = symmetry_of(whole.samples, tolerance_mm=2.0).transforms()
    out = [f.pose for f in fits]
    out += [fits[0].pose @ t for t in turns[1:] if len(turns) <= 8]
    return out


def align_nominal(model: AssemblyModel, scan: Scan, cfg: RouteConfig) -> FloatArray:
    """(4, 4) assembly -> world: the nominal ``by_design`` chose."""
    return by_design(model, scan, cfg)[0]


def expected_points(model: AssemblyModel, nominal: FloatArray, scan: Scan,
                    cfg: RouteConfig) -> dict[int, int]:
    """Per part, how many of its designed surface points the cameras would see at its
    nominal place, the other parts hiding it where they stand in front (every 2nd pixel)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    owner = []
    for i, (part, design) in enumerate(zip(model.parts, model.design, strict=True)):
        vertices = apply_pose(nominal @ design, part.mesh.vertices)
        scene.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(vertices, np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(part.mesh.triangles, np.uint32)))
        owner.append(i)
    counts = dict.fromkeys(range(len(model.parts)), 0)
    for cam in scan.cameras:
        k = cam.intrinsics
        u, v = np.meshgrid(np.arange(0, k.width, 2), np.arange(0, k.height, 2))
        dirs = np.column_stack([(u.ravel() - k.cx) / k.fx, (v.ravel() - k.cy) / k.fy,
                                np.ones(u.size)])
        dirs = (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)) @ cam.world_to_camera[:3, :3]
        rays = np.hstack([np.broadcast_to(cam.centre, dirs.shape), dirs]).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
        geometry = hit["geometry_ids"].numpy()
        found = np.isfinite(hit["t_hit"].numpy())
        ids, n = np.unique(geometry[found], return_counts=True)
        for g, c in zip(ids, n, strict=True):
            counts[owner[int(g)]] += int(c) * 4  # every 2nd pixel each way
    return counts


def _agreement(part: PartSurface, pose: FloatArray, scan: Scan, cfg: RouteConfig,
               hidden_by: tuple[Occluders, int]) -> float:
    """The share of what the cameras would see of the part at ``pose`` that the depth does
    not see past (``scan.consistency``): below ``cfg.absent_below``, the camera saw through
    where it would stand."""
    seen, _ = visible(part, pose, scan.cameras, cfg.register.stride, hidden_by)
    return consistency(seen, scan)


def _explained(part: PartSurface, pose: FloatArray, scan: Scan, cfg: RouteConfig,
               hidden_by: tuple[Occluders, int] | None = None,
               seen: FloatArray | None = None) -> npt.NDArray[np.bool_]:
    """(n,) bool: the scan's points within the fine distance of what the cameras see of the
    part at ``pose`` (``seen``: those points, where a fit at ``pose`` has cast them already)."""
    explained = np.zeros(len(scan.points), dtype=bool)
    model_pts = visible(part, pose, scan.cameras, cfg.register.stride, hidden_by)[0] \
        if seen is None else seen
    if not len(model_pts):
        return explained
    # only points within the part's reach of its centre can be that near what it shows
    reach = part.radius + cfg.register.fine_mm + 1e-3
    near = scan.near(apply_pose(pose, part.centre), reach)
    dist, _ = seen_tree(model_pts).query(scan.points[near],
                                      distance_upper_bound=cfg.register.fine_mm)
    explained[near] = np.isfinite(dist)
    return explained


def explained_share(model: AssemblyModel, scan: Scan, parts: Mapping[int, PartAsBuilt],
                    cfg: RouteConfig) -> float:
    """The share of the scan's points within the fine distance of what the cameras see of the
    placed parts (each hidden where the others stand in front)."""
    placed = {i: p.pose for i, p in parts.items() if p.pose is not None}
    if not placed or not len(scan.points):
        return 0.0
    others = occluders([(i, model.parts[i].mesh, pose) for i, pose in placed.items()])
    used = np.zeros(len(scan.points), dtype=bool)
    for i, pose in placed.items():
        used |= _explained(model.parts[i], pose, scan, cfg, (others, i))
    return float(used.mean())


def _uncertainty(part: PartSurface, fit: Fit, cfg: RouteConfig, views: int
                 ) -> PoseUncertainty:
    widen = cfg.several_views_sigma ** 2 if views > 1 else 1.0
    return pose_uncertainty(fit.hessian, fit.rmse_mm, fit.inliers, fit.centre,
                            max(part.diameter / 2, 1.0), cfg.correlated_points * widen)


# ---------------------------------------------------------------- the search route


@dataclass(frozen=True)
class Found:
    """A segment registered by the search route: its instance, the part index it was given,
    its fit, and the standard deviations of its pose's shift and turn in the least held
    observable directions (``PoseUncertainty.shift_sigma_mm``, ``turn_sigma_deg``; inf where
    the fit holds no inliers)."""

    segment: int
    index: int
    fit: Fit
    sigma_mm: float = math.inf
    sigma_deg: float = math.inf


def by_search(model: AssemblyModel, scan: Scan, cfg: RouteConfig = RouteConfig()
              ) -> list[Found]:
    """Each segment of the scan registered to the part shape that fits it best, found without
    any prior pose; then each given the name of one part of that shape (``name_parts``).

    Raises:
        ValueError: a scan without segments (the search route reads segmented clouds).
    """
    if not scan.segments:
        raise ValueError("the search route needs a segmented scan (instance ids)")
    candidates = [(shape, model.parts[members[0]])
                  for shape, members in _shape_members(model).items()]
    by_segment: dict[int, tuple[str, Fit]] = {}
    for segment, idx in sorted(scan.segments.items()):
        points = scan.points[idx]
        if len(points) >= 10:
            best = best_shape(candidates, points, scan, cfg, segment, scan.sigma_of(idx))
            if best is not None:
                by_segment[segment] = best
    out = []
    for f in name_parts(model, by_segment):
        sure = _uncertainty(model.parts[f.index], f.fit, cfg, len(scan.cameras))
        out.append(replace(f, sigma_mm=sure.shift_sigma_mm(), sigma_deg=sure.turn_sigma_deg()))
    return out


def best_shape(candidates: Sequence[tuple[str, PartSurface]], points: FloatArray, scan: Scan,
               cfg: RouteConfig, segment: int | None = None, sigma: FloatArray | None = None
               ) -> tuple[str, Fit] | None:
    """The candidate shape (a key and a surface of it) that fits a segment best, found without
    any prior pose. Shapes the segment could be (no smaller than its extent) are tried nearest
    its size first, and the search stops at a good fit (past the shapes a small segment is
    tried on: ``RouteConfig.alike_window``): a part many times the segment's size would have to
    hide nearly all of itself to show only it. ``sigma``: the points' depth sigmas
    (``register.refine``)."""
    extent = _extent(points)
    fitting = sorted((c for c in candidates if extent <= c[1].diameter + cfg.extent_slack_mm),
                     key=lambda c: c[1].diameter)
    fitness, coverage = cfg.good_fit
    if segment is not None:
        coverage = cfg.good_owned
    alike = cfg.alike_window * extent + cfg.extent_slack_mm if extent < cfg.alike_below_mm \
        else 0.0
    # past ``many_times`` the segment's extent a fit the depth alone does not contradict ends
    # the search too
    many = cfg.many_times * extent + cfg.extent_slack_mm
    best: tuple[str, Fit] | None = None
    unseen = 0.0  # the best fit's share of its visible CAD the depth alone does not contradict
    for shape, surface in fitting:
        if best is not None and best[1].fitness >= fitness and surface.diameter > alike and (
                best[1].consistent >= coverage
                or (surface.diameter > many and unseen >= cfg.good_fit[1])):
            break
        fit = global_search(surface, points, scan.cameras, cfg.register,
                            lambda seen: consistency(seen, scan), sigma)[0]
        plain = fit.consistent
        if segment is not None:  # the shapes compete on what their surface claims
            seen, _ = visible(surface, fit.pose, scan.cameras, cfg.register.stride)
            fit = replace(fit, consistent=consistency(seen, scan, segment=segment))
        if best is None or (_better(fit, best[1]) if segment is not None
                            else fit.rank() > best[1].rank()):
            best, unseen = (shape, fit), plain
    return best


def _better(fit: Fit, than: Fit, within: float = 0.05) -> bool:
    """Whether a segment's fit to one shape beats its fit to another: by the share of the
    segment it explains times the share of its surface no depth nor other segment
    contradicts, and where those are within ``within`` of each other, by the lower inlier RMS
    (a shape a little smaller than the segment's part covers all it shows of itself, at twice
    the sensor's residual)."""
    score, other = fit.fitness * fit.consistent, than.fitness * than.consistent
    return score > other + within or (score >= other - within
                                      and settled(fit.rmse_mm) < settled(than.rmse_mm))


def _shape_members(model: AssemblyModel) -> dict[str, list[int]]:
    out: dict[str, list[int]] = {}
    for i, shape in enumerate(model.shapes):
        out.setdefault(shape, []).append(i)
    return out


def _extent(points: FloatArray) -> float:
    """The cloud's largest width: over its principal axes and the 10 directions between them
    (the cube's edge and corner diagonals in their frame), from the 1st to the 99th percentile
    on each (a mask's edge holds a few pixels of what lies behind). A width is never more
    than the largest distance between two of the part's points, as a box along the principal
    axes can be (the diagonal of an X-shaped frame's box is longer than either arm)."""
    centred = points - points.mean(axis=0)
    _, axes = np.linalg.eigh(centred.T @ centred)
    signs = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1),
             (0, 1, 1), (0, 1, -1), (1, 1, 1), (1, 1, -1), (1, -1, 1), (1, -1, -1)]
    directions = np.array(signs, dtype=np.float64)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    along = centred @ axes @ directions.T
    lo, hi = np.percentile(along, [1, 99], axis=0)
    return float(np.max(hi - lo))


def name_parts(model: AssemblyModel, by_segment: Mapping[int, tuple[str, Fit]]) -> list[Found]:
    """Give each registered segment the index of a part of its shape. Which copy of a shape
    (which bolt of four) a segment is follows from where the segments lie together: the
    registered poses of a few large parts, each read as each part of its shape and each of its
    symmetries, propose where the design stands in the scan; the proposal under which most
    segments' centroids lie on a designed centroid of their shape (matched, least total
    distance) names them all. It names; it moves no pose.
    """
    members = _shape_members(model)
    centres = {i: apply_pose(model.design[i], model.parts[i].centre)
               for i in range(len(model.parts))}
    found = sorted(by_segment.items())
    best: tuple[tuple[int, float], list[Found]] | None = None
    for placement in _placements(model, found, members):
        named, score = _match(model, found, members, centres, placement)
        if len(named) >= 3:  # refit the placement to the matched centroids, and match again
            refit = _rigid([(centres[f.index], f.fit.centre) for f in named])
            named, score = max([(named, score), _match(model, found, members, centres, refit)],
                               key=lambda ns: ns[1])
        if best is None or score > best[0]:
            best = (score, named)
    if best is None:
        return []
    return sorted(best[1], key=lambda f: f.index)


def _placements(model: AssemblyModel, found: Sequence[tuple[int, tuple[str, Fit]]],
                members: Mapping[str, list[int]], generators: int = 3, turns: int = 24
                ) -> list[FloatArray]:
    """Design -> scan motions proposed by the registered poses of the largest segments'
    shapes: each read as each part of its shape, through each of the part's symmetries (a
    revolved part's turn sampled ``turns`` times)."""
    by_size = sorted(found, key=lambda item: -model.parts[members[item[1][0]][0]].diameter)
    out = []
    for _, (shape, fit) in by_size[:generators]:
        for i in members[shape]:
            symmetry = model.symmetries[i]
            group = symmetry.transforms()
            step = max(1, len(group) // turns) if symmetry.continuous else 1
            pose = model.as_part(i, fit.pose)
            for turn in group[::step][:2 * turns]:
                out.append(pose @ turn @ np.linalg.inv(model.design[i]))
    return out


def _match(model: AssemblyModel, found: Sequence[tuple[int, tuple[str, Fit]]],
           members: Mapping[str, list[int]], centres: Mapping[int, FloatArray],
           placement: FloatArray) -> tuple[list[Found], tuple[int, float]]:
    """Segments matched to parts of their shape under a placement (least total distance
    between registered and placed designed centroids) and the match's score: how many lie
    within a quarter of their part's diameter (5 mm at least), then -the total distance."""
    named: list[Found] = []
    close, total = 0, 0.0
    by_shape: dict[str, list[tuple[int, Fit]]] = {}
    for segment, (shape, fit) in found:
        by_shape.setdefault(shape, []).append((segment, fit))
    for shape, segs in by_shape.items():
        candidates = members[shape]
        where = np.array([apply_pose(placement, centres[i]) for i in candidates])
        cost = np.round(np.linalg.norm(np.array([f.centre for _, f in segs])[:, None]
                                       - where[None], axis=2), 6)  # (``settled``)
        rows, cols = linear_sum_assignment(cost)
        reach = max(5.0, model.parts[candidates[0]].diameter / 4)
        for r, c in zip(rows, cols, strict=True):
            fit = segs[r][1]
            named.append(Found(segs[r][0], candidates[c],
                               replace(fit, pose=model.as_part(candidates[c], fit.pose))))
            close += int(cost[r, c] <= reach)
            total += float(cost[r, c])
    return named, (close, -total)


def _rigid(pairs: Sequence[tuple[FloatArray, FloatArray]]) -> FloatArray:
    """(4, 4) the least-squares rigid motion taking the first points onto the second (Kabsch)."""
    src = np.array([p for p, _ in pairs])
    dst = np.array([q for _, q in pairs])
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    u, _, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1, 1, d]) @ u.T
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = cd - rot @ cs
    return out


def size_signature(part: PartSurface) -> FloatArray:
    """(4,) a part's width and the principal spreads of its surface samples (mm), all alike
    however the part is turned: parts whose signatures agree within a tolerance are one shape
    to a camera. The width is the largest distance between two of its vertices (its
    ``diameter``, a box diagonal in the assembly's axes, would tell a washer laid flat from
    the same washer tilted)."""
    centred = part.samples - part.centre
    spreads = np.sqrt(np.maximum(np.linalg.eigvalsh(centred.T @ centred / len(centred)), 0))
    return np.array([width(part.mesh.vertices), *spreads])


def width(vertices: FloatArray) -> float:
    """The largest distance between two of the points (over their convex hull's corners)."""
    from scipy.spatial import ConvexHull, QhullError
    from scipy.spatial.distance import pdist

    points = np.unique(np.asarray(vertices, dtype=np.float64), axis=0)
    if len(points) < 2:
        return 0.0
    try:
        points = points[ConvexHull(points).vertices]
    except QhullError:  # flat or degenerate: every point is a candidate
        pass
    if len(points) > 4000:  # a hull of many corners: a seeded draw of them
        points = points[np.random.default_rng(0).choice(len(points), 4000, replace=False)]
    return float(pdist(points).max())


def shape_keys(parts: Sequence[PartSurface], symmetries: Sequence[Symmetry],
               tolerance_mm: float = 1.0) -> tuple[str, ...]:
    """Per part, the key of the parts a camera cannot tell apart from it: a width and
    principal spreads (``size_signature``) within ``tolerance_mm`` of the first such part's
    (about the sensor's noise at 0.6 m: a bolt 2 mm longer than its neighbours is the same
    bolt to it; a plate and its mirror image are one plate), never of a later one's (a row of
    parts each a little larger than the last is not one shape). The key names that first
    part, and its symmetry."""
    keys: list[str] = []
    first: list[tuple[str, FloatArray]] = []
    for part, symmetry in zip(parts, symmetries, strict=True):
        size = size_signature(part)
        for key, other in first:
            if np.all(np.abs(size - other) <= tolerance_mm):
                keys.append(key)
                break
        else:
            key = f"{part.part_id}:{symmetry.order if symmetry.axis else 1}:" \
                  f"{symmetry.flip is not None}"
            first.append((key, size))
            keys.append(key)
    return tuple(keys)


def alike_transforms(parts: Sequence[PartSurface], shapes: Sequence[str],
                     onto: Callable[[PartSurface, PartSurface], FloatArray] | None = None
                     ) -> tuple[FloatArray, ...]:
    """Per part, the motion of its frame onto the first part of its shape's (identity for
    that one), by ``onto`` (default ``onto_alike``; a caller may remember its answers)."""
    first: dict[str, int] = {}
    out = []
    for i, (part, shape) in enumerate(zip(parts, shapes, strict=True)):
        j = first.setdefault(shape, i)
        out.append(np.eye(4) if j == i else (onto or onto_alike)(part, parts[j]))
    return tuple(out)


def onto_alike(part: PartSurface, other: PartSurface) -> FloatArray:
    """(4, 4) the motion of ``part``'s frame that lays its surface on ``other``'s (two parts
    of one shape): the Kabsch fit of their vertices where the meshes are one mesh moved (a
    part instanced several times), else the least-RMS of the turns that put principal axes
    on principal axes, refined by ICP on the samples."""
    a, b = part.mesh.vertices, other.mesh.vertices
    if a.shape == b.shape:
        motion = _rigid(list(zip(a, b, strict=True)))
        if float(np.abs(apply_pose(motion, a) - b).max()) < 1e-3 * max(part.diameter, 1.0):
            return motion
    from cadio.inspect.register import align_samples

    return align_samples(part, other)


def visible_share(model: AssemblyModel, poses: Mapping[int, FloatArray],
                  cameras: Sequence[Camera]) -> dict[int, float]:
    """Per part at its pose, the share of its surface samples the cameras see, the other parts
    hiding it (a sample is seen when the ray to it first meets it there)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    order = sorted(poses)
    for i in order:
        vertices = apply_pose(poses[i], model.parts[i].mesh.vertices)
        scene.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(vertices, np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(model.parts[i].mesh.triangles,
                                                            np.uint32)))
    out = {}
    for geometry, i in enumerate(order):
        part = model.parts[i]
        pts = apply_pose(poses[i], part.samples[::10])
        normals = part.normals[::10] @ poses[i][:3, :3].T
        seen = np.zeros(len(pts), dtype=bool)
        for cam in cameras:
            to = pts - cam.centre
            dist = np.linalg.norm(to, axis=1)
            dirs = to / dist[:, None]
            facing = np.einsum("ij,ij->i", normals, dirs) < 0
            rays = np.hstack([np.broadcast_to(cam.centre, dirs.shape), dirs]).astype(np.float32)
            hit = scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
            first = hit["geometry_ids"].numpy() == geometry
            near = np.abs(hit["t_hit"].numpy() - dist) < max(0.5, 1e-3 * float(dist.mean()))
            uv, z = cam.project(pts)
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.intrinsics.width) & (uv[:, 1] >= 0) & (
                uv[:, 1] < cam.intrinsics.height) & (z > 0)
            seen |= facing & first & near & inside
        out[i] = float(seen.mean())
    return out

