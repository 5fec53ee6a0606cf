"""Points sampled on a part's CAD surfaces, and the exact normals of the B-rep faces under them.

The ``truth`` input of the relation stage is the CAD itself: area-uniform samples of the part's
tessellation. Its pair evidence (``cadio.evidence.fits``) reads each point's normal. Estimated by
local PCA, a normal tilts by degrees on a short arc, and a facet of a large cylinder is flat: a
strip of a bore a few samples wide then passes for a plane, and the part's dominant plane
direction (what ``parallel`` and ``perpendicular`` are decided on) comes out wrong. The B-rep
knows the surface under every sample, so the truth's evidence takes its normals from there:

- each sample lies on one triangle of the mesh, and near the face that triangle meshes;
- the candidates are the part's planar faces (``Features.planes``: normal and offset per face)
  and cylindrical faces (``Features.axes``: axis line and radius per face);
- a sample takes the normal of the nearest candidate surface whose normal there is within
  ``AGREE_DEG`` of its triangle's normal (a facet departs from its face by at most the mesher's
  angular deflection), if that surface is within ``reach_mm`` of it (the mesher's chordal
  deviation, with room); otherwise the triangle's normal (freeform, conical, spherical and
  toroidal faces, where the facets are the best the features know).

Every sample keeps its position: only the normal is exact. Normals point out of the part.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np
import numpy.typing as npt

from cadio.records import Features, FloatArray, Mesh

__all__ = ["AGREE_DEG", "exact_normals", "placed_cad_samples", "placed_surface_samples",
           "sample_triangles", "surface_samples"]

AGREE_DEG = 25.0
REACH_MM, REACH_OF_DIAGONAL = 0.2, 0.003


def sample_triangles(mesh: Mesh, k: int, seed: int
                     ) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """k points uniformly on a mesh's surface (area-weighted triangles), its unit (mm), and the
    triangle each lies on.

    Raises:
        ValueError: a mesh without area.
    """
    tri = mesh.vertices[mesh.triangles]  # (t, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not np.isfinite(area.sum()) or area.sum() <= 0:
        raise ValueError("mesh has no surface area to sample")
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(tri), size=k, p=area / area.sum())
    u, v = rng.random((2, k))
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    t = tri[pick]
    points = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return np.asarray(points), np.asarray(pick, dtype=np.int64)


def surface_samples(mesh: Mesh, k: int, seed: int) -> FloatArray:
    """k points uniformly on a mesh's surface (area-weighted triangles), its unit (mm).

    Raises:
        ValueError: a mesh without area.
    """
    return sample_triangles(mesh, k, seed)[0]


def _seed(part_id: str) -> int:
    return int(hashlib.sha256(part_id.encode()).hexdigest()[:8], 16)


def placed_surface_samples(mesh: Mesh, part_id: str, pose_mm: FloatArray, k: int,
                           scale: float) -> FloatArray:
    """k surface samples of a part moved by ``pose_mm`` (4, 4) and scaled by ``scale``
    (world units per mm), seeded by its part id: every route to a part's CAD samples (the
    corpus, its relation dataset, the nightly) draws the same points."""
    local = surface_samples(mesh, k, _seed(part_id))
    return np.asarray((local @ pose_mm[:3, :3].T + pose_mm[:3, 3]) * scale)


def placed_cad_samples(mesh: Mesh, features: Features, part_id: str, pose_mm: FloatArray,
                       k: int, scale: float) -> npt.NDArray[np.float32]:
    """(k, 6) float32: the same samples as ``placed_surface_samples`` (world units), each with
    its exact outward unit normal (``exact_normals``) turned by the pose.

    ``features``: the part's B-rep features in its own frame (as ingest wrote them)."""
    local, tris = sample_triangles(mesh, k, _seed(part_id))
    normals = exact_normals(local, facet_normals(mesh)[tris], features)
    rot = pose_mm[:3, :3]
    points = (local @ rot.T + pose_mm[:3, 3]) * scale
    return np.hstack([points, normals @ rot.T]).astype(np.float32)


def facet_normals(mesh: Mesh) -> FloatArray:
    """(t, 3) outward unit normals of the mesh's triangles (zero for a degenerate one)."""
    tri = mesh.vertices[mesh.triangles]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(cross, axis=1, keepdims=True)
    return np.asarray(np.divide(cross, norm, out=np.zeros_like(cross), where=norm > 0))


def exact_normals(points: FloatArray, facet: FloatArray, features: Features,
                  reach_mm: float | None = None) -> FloatArray:
    """(n, 3) outward unit normals of the B-rep faces under ``points`` (n, 3) mm, part frame.

    Args:
        facet: (n, 3) the outward normal of each point's triangle; it picks among the surfaces
            near a point, gives the sign, and stands in where no plane or cylinder is near.
        features: the part's B-rep features, same frame.
        reach_mm: how far a point may be from its surface; by default the larger of
            ``REACH_MM`` and ``REACH_OF_DIAGONAL`` of the part's bounding-box diagonal.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    facet = np.asarray(facet, dtype=np.float64).reshape(-1, 3)
    out = facet.copy()
    if reach_mm is None:
        diagonal = float(np.linalg.norm(np.asarray(features.bbox_max) -
                                        np.asarray(features.bbox_min)))
        reach_mm = max(REACH_MM, REACH_OF_DIAGONAL * diagonal)
    cos = math.cos(math.radians(AGREE_DEG))
    best = np.full(len(pts), np.inf)
    for group in features.planes:
        n = np.asarray(group.normal, dtype=np.float64)
        facing = facet @ n
        agree = np.abs(facing) >= cos
        along = pts @ n
        for offset in group.offsets:
            dist = np.abs(along - offset)
            take = agree & (dist < best) & (dist <= reach_mm)
            best[take] = dist[take]
            out[take] = np.sign(facing[take])[:, None] * n
    for axis in features.axes:
        if axis.kind != "cylinder":
            continue
        u = np.asarray(axis.direction, dtype=np.float64)
        rel = pts - np.asarray(axis.point, dtype=np.float64)
        radial = rel - np.outer(rel @ u, u)
        r = np.linalg.norm(radial, axis=1)
        normal = np.divide(radial, r[:, None], out=np.zeros_like(radial), where=r[:, None] > 0)
        towards = np.einsum("ij,ij->i", normal, facet)
        agree = (np.abs(towards) >= cos) & (r > 0)
        for radius in axis.radii:
            dist = np.abs(r - radius)
            take = agree & (dist < best) & (dist <= reach_mm)
            best[take] = dist[take]
            out[take] = np.sign(towards[take])[:, None] * normal[take]
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.asarray(np.divide(out, norm, out=np.zeros_like(out), where=norm > 0))
