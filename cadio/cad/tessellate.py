"""Tessellation of B-rep shapes into watertight triangle meshes, and exact and mesh volumes.

Downstream stages (voxelization, rendering of RGB-D views) work on triangles, so this is the one
place where a B-rep becomes a mesh. OpenCascade meshes each face separately; the triangles are
gathered here with the face location applied and the winding flipped on REVERSED faces, so all
of them run counter-clockwise seen from outside. Nodes shared by neighbouring faces are merged
so that a closed solid gives a closed mesh, whose divergence volume then matches the B-rep's.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import numpy.typing as npt
from OCP.Bnd import Bnd_Box
from OCP.BRep import BRep_Tool
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepGProp import BRepGProp
from OCP.BRepMesh import BRepMesh_IncrementalMesh
from OCP.BRepTools import BRepTools
from OCP.GProp import GProp_GProps
from OCP.TopAbs import TopAbs_FACE, TopAbs_REVERSED
from OCP.TopExp import TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from cadio.errors import GeometryError
from cadio.records import Mesh
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances

log = logging.getLogger(__name__)

# Nodes closer than this are one vertex. OpenCascade takes the boundary nodes of each face from
# the shared edge discretisation, so true duplicates agree to ~1e-12 mm; 1e-6 mm stays far below
# any feature of a real part (OCCT's own Precision::Confusion is 1e-7 mm).
MERGE_DISTANCE_MM = 1e-6
# Relative accuracy asked of OCCT's adaptive mass-property integration. The default fixed Gauss
# rule is off by ~1% on coarse rational B-splines (a NURBS-converted cylinder); the adaptive rule
# costs 2-5x, and is within ~1e-6 on volumes and areas. It controls the error of the mass only:
# centroids may be off by up to ~5e-5 of the part's size (abc_00509765, part 6). Its cost sits in
# rational B-spline faces with many knot spans (abc_00001511: 8 s for one face of 212 spans);
# ingest integrates those in cadio.cad.integrate instead (1.2 s, to ~1e-9), and each face once
# for its area and the part's volume. Analytic faces, where the default rule is exact, cost it
# little (the default would save ~3% of the integration there).
MASS_PROPS_REL_EPS = 1e-6

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]


def tessellate(shape: TopoDS_Shape, tol: Tolerances = DEFAULT_TOLERANCES) -> Mesh:
    """Mesh a shape into outward, counter-clockwise triangles with merged vertices.

    Any existing triangulation is discarded first, so the result depends only on ``tol``.

    Args:
        shape: a solid (or any shape with faces), millimetres.
        tol: ``mesh_linear_mm`` / ``mesh_relative`` (chordal deviation, see
            ``linear_deflection``) and ``mesh_angular_rad`` are used.

    Returns:
        The mesh: vertices (n, 3) float64 mm, triangles (m, 3) int64, watertight for a closed
        solid.

    Raises:
        GeometryError: when meshing yields no triangle at all.
    """
    BRepTools.Clean_s(shape)
    deflection = linear_deflection(shape, tol)
    BRepMesh_IncrementalMesh(shape, deflection, False, tol.mesh_angular_rad, True)
    vertices, triangles, missing = _gather_faces(shape)
    if len(triangles) == 0:
        raise GeometryError("tessellation", "meshing produced no triangles")
    merged = merge_vertices(Mesh(vertices=vertices, triangles=triangles))
    return replace(merged, missing_faces=missing)


def _gather_faces(shape: TopoDS_Shape) -> tuple[FloatArray, IntArray, int]:
    """Per-face triangulations concatenated (located, winding oriented) + faces left out."""
    all_vertices: list[FloatArray] = []
    all_triangles: list[IntArray] = []
    offset = 0
    missing = 0
    explorer = TopExp_Explorer(shape, TopAbs_FACE)
    while explorer.More():
        face = TopoDS.Face_s(explorer.Current())
        explorer.Next()
        got = _face_triangles(face)
        if got is None:
            missing += 1
            continue
        vertices, triangles = got
        all_vertices.append(vertices)
        all_triangles.append(triangles + offset)
        offset += len(vertices)
    if missing:
        log.warning("%d face(s) have no triangulation and are left out of the mesh", missing)
    if not all_triangles:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), missing
    return np.concatenate(all_vertices), np.concatenate(all_triangles), missing


def _face_triangles(face: TopoDS_Face) -> tuple[FloatArray, IntArray] | None:
    """One face's nodes (mm, located) and 0-based triangles, or None when it has no mesh."""
    location = TopLoc_Location()
    poly = BRep_Tool.Triangulation_s(face, location)
    if poly is None or poly.NbTriangles() == 0:
        return None
    count = range(1, poly.NbNodes() + 1)
    if location.IsIdentity():  # most faces of a single part: no copy through an identity
        vertices = np.array([poly.Node(i).Coord() for i in count], dtype=np.float64)
    else:
        trsf = location.Transformation()
        vertices = np.array([poly.Node(i).Transformed(trsf).Coord() for i in count],
                            dtype=np.float64)
    triangles = np.array(
        [poly.Triangle(i).Get() for i in range(1, poly.NbTriangles() + 1)], dtype=np.int64
    ) - 1
    if face.Orientation() == TopAbs_REVERSED:
        triangles = triangles[:, ::-1]
    return vertices, np.ascontiguousarray(triangles)


def linear_deflection(shape: TopoDS_Shape, tol: Tolerances = DEFAULT_TOLERANCES) -> float:
    """Chordal deviation for ``shape``: ``mesh_linear_mm``, less for small parts, more for huge.

    A fixed 0.1 mm sag costs a 3 mm bearing ball ~6% of its volume, and gives a 200 m part
    millions of triangles. The sag is kept between ``mesh_relative_coarse`` and
    ``mesh_relative`` of the bounding-box diagonal, so every part is meshed to a similar
    relative accuracy; parts of ~40-200 mm get exactly ``mesh_linear_mm``.
    """
    box = Bnd_Box()
    # The box of the unplaced shape: the same part gets the same mesh wherever it is placed.
    BRepBndLib.Add_s(shape.Located(TopLoc_Location()), box)
    if box.IsVoid():
        return tol.mesh_linear_mm
    diagonal = float(np.sqrt(box.SquareExtent()))
    fine = min(tol.mesh_linear_mm, max(tol.mesh_relative * diagonal, 1e-3))
    return max(fine, tol.mesh_relative_coarse * diagonal)


def merge_vertices(mesh: Mesh, distance: float = MERGE_DISTANCE_MM) -> Mesh:
    """Merge vertices closer than ``distance`` and drop triangles that collapse.

    Args:
        mesh: any triangle mesh.
        distance: mm; vertices within it (transitively) become one.

    Returns:
        A mesh whose vertices are the first of each merged cluster, in their original order.
    """
    n = len(mesh.vertices)
    pairs = cKDTree(mesh.vertices).query_pairs(distance, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    # Keep the first vertex of each cluster and renumber clusters by that vertex's position.
    first = np.full(labels.max() + 1, n, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(n))
    order = np.argsort(first)
    new_index = np.empty_like(order)
    new_index[order] = np.arange(len(order))
    triangles = new_index[labels[mesh.triangles]]
    keep = (
        (triangles[:, 0] != triangles[:, 1])
        & (triangles[:, 1] != triangles[:, 2])
        & (triangles[:, 0] != triangles[:, 2])
    )
    return Mesh(vertices=mesh.vertices[first[order]], triangles=triangles[keep].astype(np.int64))


def mesh_volume(mesh: Mesh) -> float:
    """Signed enclosed volume by the divergence theorem.

    Args:
        mesh: a closed mesh with outward counter-clockwise triangles, mm.

    Returns:
        Volume in mm^3 (negative when the triangles face inwards).
    """
    v = mesh.vertices[mesh.triangles]  # (m, 3, 3)
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def brep_volume(shape: TopoDS_Shape) -> float:
    """Exact volume of a shape from its B-rep.

    Args:
        shape: a solid or a compound of solids, mm.

    Returns:
        Volume in mm^3 (OpenCascade's sign: negative for an inside-out solid).
    """
    return brep_mass(shape)[0]


def brep_mass(shape: TopoDS_Shape) -> tuple[float, FloatArray]:
    """Exact volume and volume centroid of a shape from its B-rep, in one integration.

    The adaptive integration costs up to seconds on a part with large B-spline faces; ingest
    checks the volume and writes the centroid, so it integrates once and passes both on.

    Args:
        shape: a solid or a compound of solids, mm.

    Returns:
        (volume mm^3 with OpenCascade's sign, centroid (3,) float64 mm).
    """
    props = GProp_GProps()
    BRepGProp.VolumeProperties_s(shape, props, MASS_PROPS_REL_EPS)
    c = props.CentreOfMass()
    return float(props.Mass()), np.array([c.X(), c.Y(), c.Z()])
