"""Which parts come close: box pruning, mesh certificates and exact distances between faces.

Pruning cannot change under a rigid motion of the whole assembly: enlarged axis-aligned boxes
(``box_pairs``) skip only pairs that cannot touch (a box bounds its solid in any frame), and the
contact test (``contact_pairs``, ``in_contact``: is the B-rep distance between two solids at
most a tolerance?) is exact. Exact face-to-face distances (BRepExtrema) are costly on freeform
faces and large housings (tens of seconds for one pair of the PM4 pump), so a cheap certificate
rules pairs out first: a coarse mesh of a copy of each part (chordal deflection
``MESH_DEFLECTION_MM``) is sampled every ``SAMPLE_SPACING_MM`` and the samples' nearest
distance, less the sampling and mesh slack, is a lower bound on the true distance. Face pairs it
cannot rule out are measured exactly, the likeliest first, stopping at the first hit; the answer
is the exact test's, so it does not change when the assembly moves.

Concentric face mates need the exact distance of coaxial faces up to a millimetre
(``close_faces``); ``coaxial_bound`` rules most pairs out first, tighter there than the samples:
the faces' stations along the shared axis and distances from it, bounded from the same mesh
with its slack (a shaft nested in a ring, whose boxes overlap, is ruled out by its radii).
``ProxyCache`` builds each part's mesh once, on first use, for both; a part placed in many
scenes is meshed once in its own frame and its mesh moved (``ContactProxy.moved``).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field

import numpy as np
from OCP.Bnd import Bnd_Box
from OCP.BRep import BRep_Tool
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepBuilderAPI import BRepBuilderAPI_Copy
from OCP.BRepClass3d import BRepClass3d_SolidClassifier
from OCP.BRepExtrema import BRepExtrema_DistShapeShape
from OCP.BRepMesh import BRepMesh_IncrementalMesh
from OCP.TopAbs import TopAbs_IN, TopAbs_VERTEX
from OCP.TopExp import TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape
from scipy.spatial import cKDTree

from cadio.cad.faces import indexed_faces
from cadio.records import FloatArray, apply_pose, perpendicular_pair
from cadio.truth.contact import SLACK, PartGeometry

# Contact certificate: a coarse mesh (chordal deflection mm, or the part's size / MESH_RELATIVE
# if larger) cut into triangles no longer than the spacing (mm, or size / SAMPLE_RELATIVE); their
# centroids are the samples: every point of such a triangle is within 2/3 spacing of one.
# BRepMesh keeps the deviation near the deflection, not strictly under it: MESH_SAFETY doubles it.
MESH_DEFLECTION_MM, MESH_RELATIVE, MESH_SAFETY = 0.2, 1000.0, 2.0
SAMPLE_SPACING_MM, SAMPLE_RELATIVE = 1.5, 100.0


def box_pairs(parts: Sequence[PartGeometry], margin: float) -> list[tuple[int, int]]:
    """Pairs (i < j) whose bounding boxes, enlarged by ``margin`` mm, overlap."""
    if len(parts) < 2:
        return []
    boxes = np.array([part.box for part in parts])
    lo, hi = boxes[:, :3], boxes[:, 3:]
    hit = np.all((lo[:, None, :] <= hi[None, :, :] + margin)
                 & (lo[None, :, :] <= hi[:, None, :] + margin), axis=2)
    i, j = np.nonzero(np.triu(hit, k=1))
    return list(zip(i.tolist(), j.tolist(), strict=True))


def contact_pairs(parts: Sequence[PartGeometry], boxed: Sequence[tuple[int, int]],
                  known: Collection[tuple[int, int]], tol: float,
                  proxies: ProxyCache | None = None) -> list[tuple[int, int]]:
    """Pairs of ``boxed`` within ``tol`` mm (exact): those in ``known`` (found so already: a
    coincident mate, concentric faces measured within ``tol``), else by ``in_contact``."""
    cache = ProxyCache(parts) if proxies is None else proxies
    return [(i, j) for i, j in boxed if (i, j) in known or in_contact(cache[i], cache[j], tol)]


@dataclass(frozen=True)
class ContactProxy:
    """What the contact test needs of one solid (assembly frame, mm).

    faces: in ``indexed_faces`` order; boxes: (k, 6) their axis-aligned boxes (lo, hi);
    cheap: (k,) bool, faces whose exact distances are quick (planes); triangles: per face, the
    corners (m, 3, 3) of a coarse mesh of it (None where the mesher skipped the face), cut for
    ``samples`` into triangles no longer than spacing (mm); mesh_slack: mm, the most a point of
    the part's surface can be away from its mesh; slack: mm, the most it can be away from its
    nearest sample.
    """

    shape: TopoDS_Shape
    faces: list[TopoDS_Face]
    boxes: FloatArray
    cheap: np.ndarray
    triangles: list[FloatArray | None]
    spacing: float
    mesh_slack: float
    slack: float
    _samples: dict[int, FloatArray | None] = field(default_factory=dict, repr=False)

    def samples(self, face_id: int) -> FloatArray | None:
        """Points (n, 3) on the face's mesh, every point of the face within ``slack`` of one
        (cut on first use: most faces are never asked for)."""
        if face_id not in self._samples:
            tri = self.triangles[face_id]
            self._samples[face_id] = None if tri is None else _bisect(tri, self.spacing).mean(
                axis=1)
        return self._samples[face_id]

    def revolution_box(self, face_id: int, point: FloatArray, direction: FloatArray
                       ) -> FloatArray | None:
        """(t_lo, t_hi, rho_lo, rho_hi) mm: bounds on the face's stations along the line
        (point, unit direction) and on its distances from it, or None without a mesh.

        Stations are linear, so a triangle's lie between its corners'; distances are convex, so
        a triangle's largest is at a corner and its smallest is that of its shadow on the plane
        across the line; each bound then widens by ``mesh_slack``.
        """
        tri = self.triangles[face_id]
        if tri is None:
            return None
        rel = tri - point
        t = rel @ direction
        across = rel - t[..., None] * direction
        e1, e2 = perpendicular_pair(direction)
        shadow = np.stack([across @ e1, across @ e2], axis=-1)  # (m, 3, 2)
        rho = np.linalg.norm(across, axis=2)
        near = float(_origin_to_triangles(shadow).min())
        return np.array([t.min() - self.mesh_slack, t.max() + self.mesh_slack,
                         max(0.0, near - self.mesh_slack), rho.max() + self.mesh_slack])

    def moved(self, pose: FloatArray, shape: TopoDS_Shape, faces: list[TopoDS_Face],
              boxes: FloatArray) -> ContactProxy:
        """This proxy after the rigid motion ``pose`` (4, 4), for the moved shape, its faces
        and their boxes (distances, hence the slacks, do not change)."""
        if np.array_equal(pose, np.eye(4)):
            return self
        triangles = [None if t is None else apply_pose(pose, t) for t in self.triangles]
        return ContactProxy(shape, faces, boxes, self.cheap, triangles, self.spacing,
                            self.mesh_slack, self.slack)


class PartModel:
    """A part described once in its own frame (``cadio.truth.contact.describe_shape``), with
    its face boxes and contact proxy made on first use and kept: a part placed in many scenes
    is described and meshed once."""

    def __init__(self, part: PartGeometry) -> None:
        self.part = part
        self._boxes: FloatArray | None = None
        self._proxy: ContactProxy | None = None

    def boxes(self) -> FloatArray:
        """(faces, 6) the boxes (lo, hi) of the part's faces, mm."""
        if self._boxes is None:
            self._boxes = face_boxes(self.part.faces)
        return self._boxes

    def proxy(self) -> ContactProxy:
        if self._proxy is None:
            self._proxy = contact_proxy(self.part.shape, self.part.plane_ids, self.boxes())
        return self._proxy


class ProxyCache:
    """Contact proxies of a set of placed parts, each built on first use (the mesh is the
    cost), and their face boxes, which need no mesh.

    Args:
        parts: the parts as placed.
        own: per part, its ``PartModel`` in the part's own frame and the pose (4, 4) that placed
            it; default: the parts are described where they are (an assembly's solids).
    """

    def __init__(self, parts: Sequence[PartGeometry],
                 own: Sequence[tuple[PartModel, FloatArray]] | None = None) -> None:
        self._parts = parts
        self._own = list(own) if own is not None else [(PartModel(p), np.eye(4)) for p in parts]
        self._proxies: dict[int, ContactProxy] = {}
        self._boxes: dict[int, FloatArray] = {}

    def __getitem__(self, k: int) -> ContactProxy:
        if k not in self._proxies:
            own, pose = self._own[k]
            part = self._parts[k]
            self._proxies[k] = own.proxy().moved(pose, part.shape, part.faces, self.boxes(k))
        return self._proxies[k]

    def built(self) -> int:
        """How many parts' proxies were built (asked for) so far."""
        return len(self._proxies)

    def boxes(self, k: int) -> FloatArray:
        """(faces, 6) the boxes (lo, hi) of part k's faces as placed, mm."""
        if k not in self._boxes:
            own, pose = self._own[k]
            self._boxes[k] = moved_boxes(own.boxes(), pose)
        return self._boxes[k]


def moved_boxes(boxes: FloatArray, pose: FloatArray) -> FloatArray:
    """(k, 6) boxes (lo, hi) holding the boxes (k, 6) after the rigid motion ``pose``: those of
    their moved corners (the boxes themselves under the identity)."""
    if np.array_equal(pose, np.eye(4)):
        return boxes
    pick = np.array([[x, 1 + y, 2 + z] for x in (0, 3) for y in (0, 3) for z in (0, 3)])
    corners = apply_pose(pose, boxes[:, pick])  # (k, 8, 3)
    return np.concatenate([corners.min(axis=1), corners.max(axis=1)], axis=1)


def face_boxes(faces: Sequence[TopoDS_Face]) -> FloatArray:
    """(k, 6) axis-aligned boxes (lo, hi) of the faces, mm, enlarged by their tolerances."""
    boxes = np.empty((len(faces), 6))
    for k, face in enumerate(faces):
        box = Bnd_Box()
        BRepBndLib.Add_s(face, box, False)
        boxes[k] = box.Get()
    return boxes


def contact_proxy(shape: TopoDS_Shape, cheap_ids: Sequence[int] = (),
                  boxes: FloatArray | None = None) -> ContactProxy:
    """Face boxes and mesh samples of a solid; the solid itself is not modified (a copy is meshed).

    Args:
        shape: a solid in the assembly frame, mm.
        cheap_ids: ids of faces whose exact distances are quick to compute (planar faces).
        boxes: its face boxes (``face_boxes``) where already known.
    """
    faces = indexed_faces(shape)
    boxes = face_boxes(faces) if boxes is None else boxes
    size = float(np.linalg.norm(boxes[:, 3:].max(axis=0) - boxes[:, :3].min(axis=0)))
    deflection = max(MESH_DEFLECTION_MM, size / MESH_RELATIVE)
    spacing = max(SAMPLE_SPACING_MM, size / SAMPLE_RELATIVE)
    copy = BRepBuilderAPI_Copy(shape, False, False).Shape()
    BRepMesh_IncrementalMesh(copy, deflection, False, 0.5, False)
    triangles = [_triangles(face) for face in indexed_faces(copy)]
    cheap = np.isin(np.arange(len(faces)), list(cheap_ids))
    mesh_slack = MESH_SAFETY * deflection
    return ContactProxy(shape, faces, boxes, cheap, triangles, spacing, mesh_slack,
                        2.0 * spacing / 3.0 + mesh_slack)


def in_contact(a: ContactProxy, b: ContactProxy, tol_mm: float) -> bool:
    """True when the exact distance between the two solids is at most ``tol_mm``.

    Candidate face pairs have boxes within reach; the mesh samples give each a lower bound on
    its distance, and those that may be within ``tol_mm`` are measured exactly (planar pairs
    first, then by the bound), stopping at the first hit. Solids whose boundaries stay apart
    touch only when one holds the other.
    """
    box_dist = box_distances(a.boxes[:, None, :], b.boxes[None, :, :])
    bound: dict[tuple[int, int], float] = {}
    trees: dict[int, cKDTree] = {}
    for i, j in zip(*np.nonzero(box_dist <= tol_mm), strict=True):
        lower = _sample_bound(a, int(i), b, int(j), tol_mm, trees)
        if lower <= tol_mm:
            bound[(int(i), int(j))] = lower
    ranked = sorted(bound, key=lambda ij: (not (a.cheap[ij[0]] and b.cheap[ij[1]]), bound[ij]))
    return (faces_within(a.faces, b.faces, ranked, tol_mm)
            or _holds(a.shape, b.shape) or _holds(b.shape, a.shape))


def close_faces(a: ContactProxy, b: ContactProxy, pairs: Sequence[tuple[int, int]],
                limit_mm: float) -> dict[tuple[int, int], float]:
    """Exact distances (mm) of those listed face pairs (ids in a, ids in b) within ``limit_mm``.

    Pairs whose boxes are farther apart are not measured; the others are, exactly (BRepExtrema),
    so the caller rules out what it can first (``coaxial_bound``: mesh samples, tried here too,
    cost more than they save once it has).
    """
    found = {}
    for i, j in pairs:
        if box_distances(a.boxes[i], b.boxes[j]) > limit_mm:
            continue
        dist = exact_distance(a.faces[i], b.faces[j])
        if dist <= limit_mm * (1.0 + SLACK):
            found[(i, j)] = dist
    return found


def coaxial_bound(a: ContactProxy, face_a: int, b: ContactProxy, face_b: int,
                  point: FloatArray, direction: FloatArray) -> float:
    """A lower bound (mm) on the distance between two faces, from their ``revolution_box``es
    about one line: for points x, y at stations t and distances rho from any line,
    |x - y|^2 >= (t_x - t_y)^2 + (rho_x - rho_y)^2."""
    ra = a.revolution_box(face_a, point, direction)
    rb = b.revolution_box(face_b, point, direction)
    if ra is None or rb is None:
        return 0.0
    along = max(0.0, ra[0] - rb[1], rb[0] - ra[1])
    across = max(0.0, ra[2] - rb[3], rb[2] - ra[3])
    return math.hypot(along, across)


def faces_within(faces_a: Sequence[TopoDS_Face], faces_b: Sequence[TopoDS_Face],
                 pairs: Sequence[tuple[int, int]], tol_mm: float) -> bool:
    """True when some listed face pair (ids) is within ``tol_mm`` (exact, in list order)."""
    return any(exact_distance(faces_a[i], faces_b[j]) <= tol_mm * (1.0 + SLACK)
               for i, j in pairs)


def exact_distance(fa: TopoDS_Shape, fb: TopoDS_Shape) -> float:
    """BRepExtrema's distance between two shapes, mm (infinite when it fails)."""
    dist = BRepExtrema_DistShapeShape(fa, fb)
    return float(dist.Value()) if dist.IsDone() else math.inf


def box_distances(lo_hi_a: FloatArray, lo_hi_b: FloatArray) -> FloatArray:
    """Distances between boxes (..., 6) (lo, hi), broadcast, mm."""
    gap = np.maximum(lo_hi_b[..., :3] - lo_hi_a[..., 3:], lo_hi_a[..., :3] - lo_hi_b[..., 3:])
    return np.asarray(np.linalg.norm(np.clip(gap, 0.0, None), axis=-1), dtype=np.float64)


def _sample_bound(a: ContactProxy, i: int, b: ContactProxy, j: int, limit_mm: float,
                  trees: dict[int, cKDTree]) -> float:
    """Lower bound (mm) on the distance of face i of a and face j of b from their samples: the
    nearest pair less both slacks; 0 without samples, infinite when none is within reach."""
    sa, sb = a.samples(i), b.samples(j)
    if sa is None or sb is None:
        return 0.0
    if j not in trees:
        trees[j] = cKDTree(sb)
    slack = a.slack + b.slack
    nearest, _ = trees[j].query(sa, k=1, distance_upper_bound=limit_mm + slack)
    return float(nearest.min()) - slack if np.isfinite(nearest).any() else math.inf


def _origin_to_triangles(tri: FloatArray) -> FloatArray:
    """(m,) distances from the origin to the 2D triangles (m, 3, 2), degenerate ones too."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]

    def side(p: FloatArray, q: FloatArray) -> FloatArray:  # origin left of p -> q: positive
        return np.asarray(p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0], dtype=np.float64)

    s = np.stack([side(a, b), side(b, c), side(c, a)])
    inside = np.all(s >= 0.0, axis=0) | np.all(s <= 0.0, axis=0)
    edges = np.min([_origin_to_segments(p, q) for p, q in ((a, b), (b, c), (c, a))], axis=0)
    return np.where(inside, 0.0, edges)


def _origin_to_segments(p: FloatArray, q: FloatArray) -> FloatArray:
    """(m,) distances from the origin to the segments p -> q, each (m, 2)."""
    d = q - p
    length2 = np.einsum("ij,ij->i", d, d)
    t = np.clip(-np.einsum("ij,ij->i", p, d) / np.where(length2 > 0.0, length2, 1.0), 0.0, 1.0)
    return np.asarray(np.linalg.norm(p + t[:, None] * d, axis=1), dtype=np.float64)


def _triangles(face: TopoDS_Face) -> FloatArray | None:
    """(m, 3, 3) corners of the face's mesh triangles in the shape's frame, or None."""
    loc = TopLoc_Location()
    tri = BRep_Tool.Triangulation_s(face, loc)
    if tri is None or tri.NbTriangles() == 0:
        return None
    trsf = loc.Transformation()
    nodes = np.array([tri.Node(i).Transformed(trsf).Coord()
                      for i in range(1, tri.NbNodes() + 1)])
    index = np.array([tri.Triangle(i).Get() for i in range(1, tri.NbTriangles() + 1)]) - 1
    corners: FloatArray = nodes[index]
    return corners


def _bisect(tri: FloatArray, spacing: float) -> FloatArray:
    """Split triangles (m, 3, 3) at the middle of their longest edge until no edge > spacing."""
    done = []
    while len(tri):
        length = np.linalg.norm(tri - np.roll(tri, -1, axis=1), axis=2)  # edge k: corner k, k+1
        short = length.max(axis=1) <= spacing
        done.append(tri[short])
        tri, length = tri[~short], length[~short]
        k = length.argmax(axis=1)
        turn = (k[:, None] + np.arange(3)) % 3  # longest edge first: corners 0-1
        tri = np.take_along_axis(tri, turn[:, :, None], axis=1)
        mid = 0.5 * (tri[:, 0] + tri[:, 1])
        tri = np.concatenate([np.stack([tri[:, 0], mid, tri[:, 2]], axis=1),
                              np.stack([mid, tri[:, 1], tri[:, 2]], axis=1)])
    return np.concatenate(done) if done else np.empty((0, 3, 3))


def _holds(outer: TopoDS_Shape, inner: TopoDS_Shape) -> bool:
    """True when a vertex of ``inner`` lies inside the solid ``outer``."""
    explorer = TopExp_Explorer(inner, TopAbs_VERTEX)
    if not explorer.More():
        return False
    point = BRep_Tool.Pnt_s(TopoDS.Vertex_s(explorer.Current()))
    return bool(BRepClass3d_SolidClassifier(outer, point, 1e-7).State() == TopAbs_IN)
