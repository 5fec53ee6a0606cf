"""CAD surface samples with the exact normals of their B-rep faces: the ``truth`` evidence."""

from __future__ import annotations

import numpy as np
import pytest

from cadio.cad.features import extract_features
from cadio.cad.tessellate import tessellate
from cadio.evidence.cad_samples import (
    exact_normals,
    facet_normals,
    placed_cad_samples,
    placed_surface_samples,
    sample_triangles,
)
from cadio.evidence.fits import dominant_direction, part_cloud
from cadio.evidence.pair_features import PAIR_FEATURES, pair_features, pair_features_many


@pytest.fixture(scope="module")
def solids():  # type: ignore[no-untyped-def]
    import build123d as bd

    return {
        "plate": bd.Box(60, 40, 6) - bd.Cylinder(5, 6),  # a 5 mm bore along z
        "tube": bd.Cylinder(100, 20) - bd.Cylinder(95, 20),  # a thin wall of radius 100 mm
        "pin": bd.Pos(0, 0, 10) * bd.Cylinder(5, 30),
    }


def _meshed(solid):  # type: ignore[no-untyped-def]
    return tessellate(solid.wrapped), extract_features(solid.wrapped)


def test_samples_take_their_faces_normals_not_their_facets(solids) -> None:  # type: ignore[no-untyped-def]
    mesh, features = _meshed(solids["plate"])
    points, tris = sample_triangles(mesh, 4000, 0)
    facet = facet_normals(mesh)[tris]
    normals = exact_normals(points, facet, features)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    radius = np.linalg.norm(points[:, :2], axis=1)
    bore = (radius < 5.2) & (np.abs(points[:, 2]) < 2.9)
    assert bore.sum() > 20
    radial = np.column_stack([points[bore, :2] / radius[bore, None], np.zeros(bore.sum())])
    # the bore's normals are radial and point out of the solid, into the hole
    assert np.allclose(normals[bore] @ np.array([0, 0, 1.0]), 0.0, atol=1e-9)
    assert np.allclose(np.einsum("ij,ij->i", normals[bore], radial), -1.0, atol=1e-9)
    # ... where the facets' own normals are off by degrees
    off = np.degrees(np.arccos(np.clip(-np.einsum("ij,ij->i", facet[bore], radial), -1, 1)))
    assert off.max() > 1.0
    # the top and bottom faces keep +z and -z exactly
    inside = (radius > 5.5) & (np.abs(points[:, 0]) < 29.5) & (np.abs(points[:, 1]) < 19.5)
    top, bottom = inside & (points[:, 2] > 2.999), inside & (points[:, 2] < -2.999)
    assert top.sum() > 100 and bottom.sum() > 100
    assert np.allclose(normals[top], [0, 0, 1]) and np.allclose(normals[bottom], [0, 0, -1])


def test_placed_samples_are_the_surface_samples_with_normals_turned_by_the_pose(solids) -> None:  # type: ignore[no-untyped-def]
    mesh, features = _meshed(solids["plate"])
    c, s = np.cos(0.7), np.sin(0.7)
    pose = np.array([[c, -s, 0, 10.0], [s, c, 0, -4.0], [0, 0, 1, 2.0], [0, 0, 0, 1]])
    placed = placed_cad_samples(mesh, features, "plate-0", pose, 500, 0.001)
    assert placed.shape == (500, 6) and placed.dtype == np.float32
    assert np.allclose(placed[:, :3], placed_surface_samples(mesh, "plate-0", pose, 500, 0.001),
                       atol=1e-6)
    local = placed_cad_samples(mesh, features, "plate-0", np.eye(4), 500, 1.0)
    assert np.allclose(placed[:, 3:], local[:, 3:] @ pose[:3, :3].T, atol=1e-6)


def test_no_strip_of_a_large_cylinder_passes_for_a_plane_with_exact_normals(solids) -> None:  # type: ignore[no-untyped-def]
    mesh, features = _meshed(solids["tube"])
    samples = placed_cad_samples(mesh, features, "tube", np.eye(4), 3000, 1.0)
    estimated = part_cloud(samples[:, :3])
    exact = part_cloud(samples[:, :3], normals=samples[:, 3:])

    def across_axis(cloud):  # type: ignore[no-untyped-def]
        return [n for n, _ in cloud.planes if abs(n[2]) < 0.1]

    # the facets of a 100 mm wall are flat enough for local PCA's planes
    assert len(across_axis(estimated)) >= 3
    # with the faces' normals only the two end rings are planes, and they dominate
    assert not across_axis(exact) and len(exact.planes) == 2
    direction, ratio = dominant_direction(exact)
    assert direction is not None and abs(direction[2]) > 0.999 and ratio >= 1.5


def test_clouds_of_six_columns_bring_their_normals_to_the_pair_evidence(solids) -> None:  # type: ignore[no-untyped-def]
    (mp, fp), (mq, fq) = _meshed(solids["plate"]), _meshed(solids["pin"])
    a = placed_cad_samples(mp, fp, "plate", np.eye(4), 2000, 0.001)
    b = placed_cad_samples(mq, fq, "pin", np.eye(4), 2000, 0.001)
    many = pair_features_many([(a, b)], [1000.0])[0]
    mm = [np.asarray(c, dtype=np.float64) * [1000.0, 1000.0, 1000.0, 1.0, 1.0, 1.0]
          for c in (a, b)]
    direct = pair_features(part_cloud(mm[0][:, :3], normals=mm[0][:, 3:]),
                           part_cloud(mm[1][:, :3], normals=mm[1][:, 3:]))
    assert np.allclose(many, direct)
    without = pair_features_many([(a[:, :3], b[:, :3])], [1000.0])[0]
    assert not np.allclose(many, without)


def test_normals_must_match_the_points() -> None:
    with pytest.raises(ValueError, match="normals for"):
        part_cloud(np.zeros((10, 3)), normals=np.zeros((9, 3)))


def test_exact_planes_are_single_faces_however_curved_the_rest_of_the_part() -> None:
    """A plate whose top carries a pad 0.25 mm high, over a torus: local PCA's noise on the
    torus is about 0.4 mm, and a plane held within it merged the pad's top with the plate's.
    With the faces' normals every plane lies within ``exact_plane_mm`` of one offset, and a
    block resting on the plate beside the pad meets it 0 mm away, opposed."""
    import build123d as bd

    from cadio.evidence.fits import FeatureConfig

    plate = (bd.Box(40, 40, 4) + bd.Pos(10, 0, 2.125) * bd.Box(20, 40, 0.25)
             + bd.Pos(0, 0, -6) * bd.Torus(14, 4))
    block = bd.Pos(-10, 0, 7) * bd.Box(10, 10, 10)  # its bottom on the plate's top, z = 2
    (mp, fp), (mb, fb) = _meshed(plate), _meshed(block)
    a = placed_cad_samples(mp, fp, "plate", np.eye(4), 3000, 1.0)
    b = placed_cad_samples(mb, fb, "block", np.eye(4), 3000, 1.0)
    cloud = part_cloud(a[:, :3], normals=a[:, 3:])
    eps = FeatureConfig().exact_plane_mm
    for (normal, _), members in zip(cloud.planes, cloud.plane_members(), strict=True):
        assert np.ptp(cloud.points[members] @ normal) <= 2 * eps + 1e-9
    tops = {round(float(cloud.points[m][:, 2].mean()), 2) for (n, _), m
            in zip(cloud.planes, cloud.plane_members(), strict=True) if n[2] > 0.999}
    assert {2.0, 2.25} <= tops
    measured = pair_features(cloud, part_cloud(b[:, :3], normals=b[:, 3:]))
    f = dict(zip(PAIR_FEATURES, measured, strict=True))
    assert f["face_found"] == 1 and f["face_opposed"] == 1 and f["face_offset_mm"] < 1e-3


def test_a_pin_standing_coaxial_over_a_bore_is_no_concentric_mate(solids) -> None:  # type: ignore[no-untyped-def]
    """A pin in the plate's bore and the same axis's pin standing 1.6 mm over the plate (a
    bolt over a flange's hole, its washer between): both are coaxial with the bore, but only
    the first has faces within the CAD's 1 mm of it. On the faces' own samples the coaxial
    evidence measures the faces' gap, and the exact tests answer concentric for the first
    alone."""
    import build123d as bd

    from models.geometric import geometric_symmetric, tests_for

    over = bd.Pos(0, 0, 3 + 1.6 + 10) * bd.Cylinder(4.9, 20)
    plate = _meshed(solids["plate"])
    a = placed_cad_samples(*plate, "plate", np.eye(4), 3000, 1.0)
    cloud = part_cloud(a[:, :3], normals=a[:, 3:])
    rows = []
    for name, pin in (("in", solids["pin"]), ("over", over)):
        b = placed_cad_samples(*_meshed(pin), name, np.eye(4), 3000, 1.0)
        rows.append(pair_features(cloud, part_cloud(b[:, :3], normals=b[:, 3:])))
    f = {n: np.array([r[i] for r in rows]) for i, n in enumerate(PAIR_FEATURES)}
    assert f["coax_found"].tolist() == [1, 1]
    assert max(f["coax_spread_mm"]) < 0.05 and max(f["coax_normal_deg"]) < 1.0
    assert f["coax_face_gap_mm"][0] < 0.2 and 1.55 < f["coax_face_gap_mm"][1] < 4.0
    concentric = geometric_symmetric(np.stack(rows), tests_for("truth"))[:, 2]
    assert concentric.tolist() == [True, False]
