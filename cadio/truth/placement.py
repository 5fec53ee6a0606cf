"""How the scene generator places two parts so that a relation holds, the way assemblies do.

Poses are (4, 4) part -> world (mm), Z up. What each placement aims at (the labels come from the
truth on the placed parts, never from here):

- coincident: a planar face of each part that bounds it along its outward normal (a "rest"
  face: nothing of the part lies beyond its plane) laid face to face, a point of one face on a
  point of the other, so the faces overlap and the parts cannot interpenetrate;
- concentric: two parts on one axis line with coaxial cylinder or cone faces within
  ``concentric_gap_mm``: stacked end to end (the end faces of each part along its axis, radii
  close: discs on discs, a washer on a washer) or nested (a shaft in a bore whose radius
  exceeds it by less than the gap: a bushing on a shaft, a washer on a bolt), nested placements
  checked for interference with an exact Boolean;
- parallel / perpendicular: dominant plane directions turned vertical (or one horizontal), the
  parts apart; directional: centroids offset within the cone of an axis, the parts apart;
- touching (no relation meant): both parts turned at random and brought together until they
  touch, sharing no volume: mostly no face mate, as most touching pairs of an assembly.

Near misses sit just inside or just outside the tolerance: a lift of the upper face, a shift
of the axis, a tilt, a turn of the offset direction.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from OCP.BRepAlgoAPI import BRepAlgoAPI_Common
from OCP.BRepGProp import BRepGProp
from OCP.GProp import GProp_GProps
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS_Shape
from OCP.TopTools import TopTools_ListOfShape

from cadio.records import Features, FloatArray
from cadio.truth.contact import pose_trsf
from cadio.truth.proximity import PartModel, exact_distance

_Z = np.array([0.0, 0.0, 1.0])
# A face reaches a part's extreme along a direction within this share of the part's size.
_EXTREME_REL = 1e-6
# Nested parts interfere when their common volume exceeds this share of the smaller one.
_INTERFERENCE_REL = 1e-6
# Touching pairs: the exact gap is closed to this (a tenth of ``contact_mm``), in at most
# this many steps.
_CLOSE_MM = 0.01
_CLOSE_STEPS = 8
_BACK_OFF_STEPS = 24  # doubling from the slack: far beyond any part


# ---------------------------------------------------------------- what a part offers


@dataclass(frozen=True, eq=False)
class Rest:
    """A planar face bounding its part along its outward normal (part frame): it can rest on
    another's. triangles: (m, 3, 3) its coarse mesh, mm; area: mm^2."""

    face_id: int
    normal: FloatArray
    area: float
    triangles: FloatArray


@dataclass(frozen=True, eq=False)
class End:
    """A cylinder or cone face reaching its part's extreme along ``up`` (unit, part frame) at
    the axis point ``point``, with radius ``radius`` (mm) there: what a stack puts end to end."""

    face_id: int
    up: FloatArray
    point: FloatArray
    radius: float
    support: float


@dataclass(frozen=True, eq=False)
class Bore:
    """A cylindrical face on the axis line (``direction``, ``point``), radius mm, axial span
    (lo, hi) mm along ``direction`` from ``point``; convex: a shaft, else a hole."""

    face_id: int
    direction: FloatArray
    point: FloatArray
    radius: float
    span: tuple[float, float]
    convex: bool


@dataclass(frozen=True, eq=False)
class Offers:
    """What one part offers the coincident and concentric placements (part frame)."""

    model: PartModel
    vertices: FloatArray
    rests: tuple[Rest, ...]
    ends: tuple[End, ...]
    bores: tuple[Bore, ...]
    _scene: list[o3d.t.geometry.RaycastingScene] = field(default_factory=list, repr=False)

    @property
    def features(self) -> Features:
        return self.model.part.features

    def depth(self, points: FloatArray) -> FloatArray:
        """(n,) how deep points (n, 3) of the part frame lie inside its coarse mesh, mm
        (negative outside); the mesh misses the surface by up to its ``mesh_slack``."""
        if not self._scene:
            proxy = self.model.proxy()
            tri = np.concatenate([t for t in proxy.triangles if t is not None])
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(
                o3d.core.Tensor.from_numpy(np.ascontiguousarray(tri.reshape(-1, 3),
                                                                dtype=np.float32)),
                o3d.core.Tensor.from_numpy(np.arange(3 * len(tri), dtype=np.uint32)
                                           .reshape(-1, 3)))
            self._scene.append(scene)
        query = o3d.core.Tensor.from_numpy(np.ascontiguousarray(points, dtype=np.float32))
        return -np.asarray(self._scene[0].compute_signed_distance(query).numpy(),
                           dtype=np.float64)


def offers_of(model: PartModel) -> Offers:
    """A part's rest faces, axial ends and cylindrical faces, from its geometry and mesh."""
    part = model.part
    triangles = model.proxy().triangles
    meshed = [t for t in triangles if t is not None]
    f = part.features
    vertices = np.concatenate([t.reshape(-1, 3) for t in meshed]) if meshed else np.array(
        [[x, y, z] for x in (f.bbox_min[0], f.bbox_max[0]) for y in (f.bbox_min[1], f.bbox_max[1])
         for z in (f.bbox_min[2], f.bbox_max[2])])
    eps = _EXTREME_REL * float(np.linalg.norm(f.bbox_max - f.bbox_min))
    areas = {i: a for g in f.planes for i, a in zip(g.face_ids, g.face_areas, strict=True)}
    rests = tuple(
        Rest(fid, part.normals[k], areas.get(fid, 0.0), triangles[fid])  # type: ignore[arg-type]
        for k, fid in enumerate(part.plane_ids)
        if triangles[fid] is not None and areas.get(fid, 0.0) > 0.0
        and float((vertices @ part.normals[k]).max()) <= part.normals[k] @ part.centres[k] + eps)
    ends, bores = [], []
    for line in part.lines:
        d = line.direction
        top, bottom = float((vertices @ d).max()), float((vertices @ d).min())
        for face in line.faces:
            t = face.ends @ d
            if t[1] >= top - eps:
                ends.append(End(face.face_id, d, line.mid, float(face.radii[1]), top))
            if t[0] <= bottom + eps:
                ends.append(End(face.face_id, -d, line.mid, float(face.radii[0]), -bottom))
            if face.kind == "cylinder":
                base = float(line.mid @ d)
                bores.append(Bore(face.face_id, d, line.mid, face.radius,
                                  (float(t[0]) - base, float(t[1]) - base), face.convex))
    return Offers(model, vertices, rests, tuple(ends), tuple(bores))


# ---------------------------------------------------------------- coincident


def rest_on(a: Offers, b: Offers, lift_mm: float, rng: np.random.Generator
            ) -> tuple[FloatArray, FloatArray]:
    """b resting on a: a rest face of a turned up, one of b turned down onto it (a point of each
    face's mesh on the other's), b lifted by ``lift_mm`` (0 for contact).

    Raises:
        ValueError: a part has no rest face.
    """
    if not a.rests or not b.rests:
        raise ValueError("both parts need a rest face to lie face to face")
    fa, fb = _pick_rest(a, rng), _pick_rest(b, rng)
    ra, rb = spin(rng) @ align(fa.normal, _Z), spin(rng) @ align(fb.normal, -_Z)
    pa, pb = ra @ _point_on(fa, rng), rb @ _point_on(fb, rng)
    return pose(ra), pose(rb, pa - pb + lift_mm * _Z)


def _pick_rest(offers: Offers, rng: np.random.Generator) -> Rest:
    weights = np.array([r.area for r in offers.rests])
    return offers.rests[int(rng.choice(len(weights), p=weights / weights.sum()))]


def _point_on(rest: Rest, rng: np.random.Generator) -> FloatArray:
    """The centroid of a mesh triangle of the face, drawn by area: inside the face."""
    tri = rest.triangles
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    k = int(rng.choice(len(tri), p=area / area.sum())) if area.sum() > 0 else 0
    point: FloatArray = tri[k].mean(axis=0)
    return point


# ---------------------------------------------------------------- touching, as parts do


def touch(a: Offers, b: Offers, rng: np.random.Generator, steps: int = 32,
          rounds: int = 30, tries: int = 8) -> tuple[FloatArray, FloatArray]:
    """a against b, both turned at random, a brought in along a random direction until the
    meshes meet: a contact that is seldom a face mate (a pin against a race, a ball in a
    groove, an edge on a face), which assemblies are full of.

    From ``steps`` stations between the boxes' separation and the centres' coincidence, the
    first at which the meshes overlap is bisected (``rounds`` times) against the last apart;
    that contact is backed off until the solids are apart and the exact gap closed to within
    ``_CLOSE_MM``, so the solids touch without sharing volume. The pair's labels come from
    the exact faces, never from this. A way in that never meets (a small part passing
    through a hollow one) is drawn again, ``tries`` times at most, and the last one's
    centres are left together.
    """
    for _ in range(tries):
        ra, rb = turn(rng), turn(rng)
        u = tilt(_Z, math.degrees(math.acos(rng.uniform(-1.0, 1.0))), rng)
        placed = _bring_in(a, b, ra, rb, u, steps, rounds)
        if placed is not None:
            return placed
    return pose(ra, -ra @ a.features.centroid), pose(rb, -rb @ b.features.centroid)


def _bring_in(a: Offers, b: Offers, ra: FloatArray, rb: FloatArray, u: FloatArray,
              steps: int, rounds: int) -> tuple[FloatArray, FloatArray] | None:
    """a (turned by ra) moved along -u onto b (turned by rb, centred) until they meet; None
    when they never overlap on the way."""
    ca, cb = ra @ a.features.centroid, rb @ b.features.centroid
    pose_b = pose(rb, -cb)
    inv_b = np.linalg.inv(pose_b)

    def clearance(t: float) -> float:
        """Smallest distance between the meshes with a moved by t u (negative: overlap)."""
        pose_a = pose(ra, t * u - ca)
        b_in_a = np.linalg.solve(pose_a, pose_b)
        a_in_b = inv_b @ pose_a
        deepest = max(float(b.depth(pa @ a_in_b[:3, :3].T + a_in_b[:3, 3]).max()),
                      float(a.depth(pb @ b_in_a[:3, :3].T + b_in_a[:3, 3]).max()))
        return -deepest

    # surface samples, not only the vertices: two plates crossing like a "+" hold no vertex
    # of one inside the other
    pa, pb = _surface_samples(a), _surface_samples(b)
    va, vb = pa @ ra.T - ca, pb @ rb.T - cb
    far = float(np.ptp(va @ u) + np.ptp(vb @ u))  # boxes along u: apart from here on
    apart = far
    for t in np.linspace(far, 0.0, steps + 1)[1:]:
        if clearance(float(t)) <= 0.0:
            overlap = float(t)
            break
        apart = float(t)
    else:
        return None
    for _ in range(rounds):
        mid = 0.5 * (apart + overlap)
        if clearance(mid) > 0.0:
            apart = mid
        else:
            overlap = mid
    # The meshes miss the faces by up to their slack, and an edge may cross an edge between
    # vertices: back off until the solids are apart (a gap of exactly 0 is BRepExtrema's
    # answer for overlapping solids too), then close the exact gap d by steps of d along u,
    # which cannot make them overlap (the gap shrinks by at most the step).
    back = max(a.model.proxy().mesh_slack + b.model.proxy().mesh_slack, _CLOSE_MM)
    t, gap = apart, 0.0
    for _ in range(_BACK_OFF_STEPS):
        t += back
        gap = exact_gap(a.model, pose(ra, t * u - ca), b.model, pose_b)
        if gap > 0.0:
            break
        back *= 2.0
    for _ in range(_CLOSE_STEPS):
        if not math.isfinite(gap) or gap <= _CLOSE_MM:
            break
        t -= gap
        gap = exact_gap(a.model, pose(ra, t * u - ca), b.model, pose_b)
    return pose(ra, t * u - ca), pose_b


def _surface_samples(offers: Offers, most: int = 20_000) -> FloatArray:
    """The part's mesh vertices and its contact proxy's face samples (every point of the
    surface within the proxy's ``slack`` of one), thinned evenly to ``most``."""
    proxy = offers.model.proxy()
    found = [s for i in range(len(proxy.triangles)) if (s := proxy.samples(i)) is not None]
    points = np.concatenate([offers.vertices, *found]) if found else offers.vertices
    step = max(1, math.ceil(len(points) / most))
    return np.asarray(points[::step], dtype=np.float64)


def exact_gap(a: PartModel, pose_a: FloatArray, b: PartModel, pose_b: FloatArray) -> float:
    """The distance between two placed solids, mm (BRepExtrema; infinite when it fails)."""
    return exact_distance(_moved(a, pose_a), _moved(b, pose_b))


def _moved(model: PartModel, pose_mm: FloatArray) -> TopoDS_Shape:
    """The part's solid moved by a (4, 4) pose, mm."""
    return model.part.shape.Moved(TopLoc_Location(pose_trsf(pose_mm)))


def turn(rng: np.random.Generator) -> FloatArray:
    """A rotation drawn uniformly (a random unit quaternion)."""
    w, x, y, z = (q := rng.standard_normal(4)) / np.linalg.norm(q)
    rot: FloatArray = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    return rot


# ---------------------------------------------------------------- concentric


@dataclass(frozen=True)
class Stacked:
    """Two parts i, j of a pool to stack end to end on their ends ``first`` and ``second``."""

    i: int
    j: int
    first: End
    second: End


@dataclass(frozen=True)
class Nested:
    """Part j's shaft to nest in part i's bore (indices into a pool)."""

    i: int
    j: int
    hole: Bore
    shaft: Bore


def coaxial_choices(pool: Sequence[Offers], stack_mm: float, nest_mm: float,
                    rng: np.random.Generator, tries: int = 20,
                    nests: bool = True, nest_min_mm: float = 0.0) -> Stacked | Nested | None:
    """A random coaxial placement of two different parts of the pool: ends whose radii
    differ by at most ``stack_mm``, or (with ``nests``) a shaft ``nest_min_mm`` to ``nest_mm``
    thinner than a bore. None when ``tries`` random draws find none."""
    ends = sorted(((e.radius, i, e) for i, o in enumerate(pool) for e in o.ends),
                  key=lambda x: x[0])
    shafts = sorted(((s.radius, i, s) for i, o in enumerate(pool) for s in o.bores if s.convex),
                    key=lambda x: x[0])
    holes = [(h.radius, i, h) for i, o in enumerate(pool) for h in o.bores
             if nests and not h.convex]
    radii_e, radii_s = [r for r, _, _ in ends], [r for r, _, _ in shafts]
    for _ in range(tries):
        if holes and (not ends or rng.random() < 0.5):
            r, i, hole = holes[int(rng.integers(len(holes)))]
            lo = bisect.bisect_left(radii_s, r - nest_mm)
            hi = bisect.bisect_right(radii_s, r - nest_min_mm)
            fits = [(j, s) for _, j, s in shafts[lo:hi] if j != i]
            if fits:
                j, shaft = fits[int(rng.integers(len(fits)))]
                return Nested(i, j, hole, shaft)
        elif ends:
            r, i, end = ends[int(rng.integers(len(ends)))]
            lo = bisect.bisect_left(radii_e, r - stack_mm)
            hi = bisect.bisect_right(radii_e, r + stack_mm)
            fits_e = [(j, e) for _, j, e in ends[lo:hi] if j != i]
            if fits_e:
                j, other = fits_e[int(rng.integers(len(fits_e)))]
                return Stacked(i, j, end, other)
    return None


def stack(lower: Offers, end_a: End, upper: Offers, end_b: End, gap_mm: float,
          shift_mm: float, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """``upper`` stacked on ``lower`` on the world Z axis: the lower part's end ``end_a``
    turned up, the upper's ``end_b`` down, ``gap_mm`` apart along the axis, the upper's axis
    shifted sideways by ``shift_mm``. The parts lie in disjoint slabs: they cannot interfere."""
    ra = spin(rng) @ align(end_a.up, _Z)
    rb = spin(rng) @ align(end_b.up, -_Z)
    ta = -(ra @ end_a.point) * [1.0, 1.0, 0.0]
    tb = -(rb @ end_b.point) * [1.0, 1.0, 0.0] + shift_mm * tilt(_Z, 90.0, rng)
    tb[2] = end_a.support + end_b.support + gap_mm  # lower's top + upper's depth below its end
    return pose(ra, ta), pose(rb, tb)


def nest(holder: Offers, hole: Bore, inner: Offers, shaft: Bore, rng: np.random.Generator
         ) -> tuple[FloatArray, FloatArray] | None:
    """``inner``'s shaft in ``holder``'s hole on the world Z axis, the shaft's span centred on
    the hole's or flush with either end (in random order, either way up), the first placement
    whose parts do not interfere (exact Boolean common); None when all do."""
    ra = spin(rng) @ align(hole.direction * rng.choice([-1.0, 1.0]), _Z)
    ta = -(ra @ hole.point) * [1.0, 1.0, 0.0]
    h = sorted(float((ra @ (hole.point + t * hole.direction))[2] + ta[2]) for t in hole.span)
    for k in rng.permutation(6):
        rb = spin(rng) @ align(shaft.direction * (1.0 if k % 2 else -1.0), _Z)
        tb = -(rb @ shaft.point) * [1.0, 1.0, 0.0]
        s = sorted(float((rb @ (shaft.point + t * shaft.direction))[2]) for t in shaft.span)
        tb[2] = (0.5 * (h[0] + h[1] - s[0] - s[1]), h[0] - s[0], h[1] - s[1])[k // 2]
        pa, pb = pose(ra, ta), pose(rb, tb)
        if not _deep_inside(holder, pa, inner, pb) and \
                not interfere(holder.model, pa, inner.model, pb):
            return pa, pb
    return None


def _deep_inside(a: Offers, pose_a: FloatArray, b: Offers, pose_b: FloatArray) -> bool:
    """Whether a mesh vertex of either part lies inside the other's mesh deeper than both
    meshes' slack: surely interfering, no Boolean needed (the cheap test before the exact
    one; it may miss an interference, never invent one)."""
    slack = a.model.proxy().mesh_slack + b.model.proxy().mesh_slack
    b_in_a = np.linalg.solve(pose_a, pose_b)
    for outer, inner, rel in ((a, b, b_in_a), (b, a, np.linalg.inv(b_in_a))):
        points = inner.vertices @ rel[:3, :3].T + rel[:3, 3]
        if bool((outer.depth(points) > slack).any()):
            return True
    return False


def interfere(a: PartModel, pose_a: FloatArray, b: PartModel, pose_b: FloatArray) -> bool:
    """Whether two placed solids share volume (an exact Boolean common; touching is not
    interference). A Boolean that fails counts as interference."""
    arguments, tools = TopTools_ListOfShape(), TopTools_ListOfShape()
    arguments.Append(_moved(a, pose_a))
    tools.Append(_moved(b, pose_b))
    common = BRepAlgoAPI_Common()
    common.SetArguments(arguments)
    common.SetTools(tools)
    common.SetNonDestructive(True)  # the parts are shared by every scene
    common.Build()
    if not common.IsDone():
        return True
    props = GProp_GProps()
    BRepGProp.VolumeProperties_s(common.Shape(), props)
    smaller = min(a.part.features.volume, b.part.features.volume)
    return float(props.Mass()) > _INTERFERENCE_REL * smaller


# ---------------------------------------------------------------- rotations and poses


def pose(rot: FloatArray, t: FloatArray | Sequence[float] = (0.0, 0.0, 0.0)) -> FloatArray:
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = t
    return m


def rotation(axis: FloatArray, deg: float) -> FloatArray:
    """Rotation matrix (3, 3) about a unit axis by ``deg`` degrees (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]],
                 dtype=np.float64)
    th = math.radians(deg)
    rot: FloatArray = np.eye(3) + math.sin(th) * k + (1 - math.cos(th)) * (k @ k)
    return rot


def spin(rng: np.random.Generator) -> FloatArray:
    """A random turn about the vertical."""
    return rotation(_Z, rng.uniform(0.0, 360.0))


def align(u: FloatArray, w: FloatArray) -> FloatArray:
    """The smallest rotation (3, 3) turning unit vector u onto unit vector w."""
    u = np.asarray(u, dtype=np.float64) / np.linalg.norm(u)
    axis = np.cross(u, w)
    s, c = float(np.linalg.norm(axis)), float(np.dot(u, w))
    if s < 1e-12:  # parallel or opposite: any perpendicular axis serves for the half turn
        other = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        perp = np.cross(u, other)
        return np.eye(3) if c > 0 else rotation(perp / np.linalg.norm(perp), 180.0)
    return rotation(axis / s, math.degrees(math.atan2(s, c)))


def tilt(axis: FloatArray, deg: float, rng: np.random.Generator) -> FloatArray:
    """A unit vector at ``deg`` degrees from ``axis``, at a random azimuth about it."""
    other = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    side = np.cross(axis, other)
    side = rotation(axis, rng.uniform(0.0, 360.0)) @ (side / np.linalg.norm(side))
    th = math.radians(deg)
    tilted: FloatArray = math.cos(th) * axis + math.sin(th) * side
    return tilted
