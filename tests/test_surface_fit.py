"""Tests of cadio.cad.surface_fit: least-squares planes, cylinders and cones through samples.

Samples are drawn on exact primitives in a random pose; a fit must recover the primitive to
rounding, prefer the simplest kind, and reject a surface that none of the three fits.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cadio.cad.surface_fit import CONE, CYLINDER, PLANE, fit_primitive
from cadio.tolerances import DEFAULT_TOLERANCES as TOL

POSE = Rotation.from_euler("xyz", [23, -71, 148], degrees=True).as_matrix()
SHIFT = np.array([310.0, -42.5, 87.0])


def placed(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points and normals in the local frame (axis +Z) moved to the test pose."""
    return points @ POSE.T + SHIFT, normals @ POSE.T


def revolution(radius_at: float, slope: float, arc: float = 2 * math.pi, z0: float = 0.0,
               z1: float = 12.0, n: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """Samples of the surface r(z) = radius_at + slope * z about +Z, on an n x n grid."""
    phi, z = np.meshgrid(np.linspace(0.0, arc, n), np.linspace(z0, z1, n))
    phi, z = phi.ravel(), z.ravel()
    r = radius_at + slope * z
    radial = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
    normals = radial - slope * np.array([0.0, 0.0, 1.0])
    return placed(radial * r[:, None] + np.outer(z, [0, 0, 1]),
                  normals / np.linalg.norm(normals, axis=1)[:, None])


def test_plane_is_recovered_and_preferred() -> None:
    u, v = np.meshgrid(np.linspace(-5, 5, 9), np.linspace(0, 30, 9))
    points = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1)
    found = fit_primitive(*placed(points, np.tile([0.0, 0.0, 1.0], (u.size, 1))),
                          TOL.freeform_fit_mm)
    assert found is not None and found.kind == PLANE
    assert abs(float(found.direction @ (POSE @ [0, 0, 1]))) == pytest.approx(1.0, abs=1e-12)
    assert found.deviation <= 1e-9


@pytest.mark.parametrize("arc", [2 * math.pi, math.pi / 3])
def test_cylinder_is_recovered_whole_or_as_a_sixth(arc: float) -> None:
    found = fit_primitive(*revolution(7.5, 0.0, arc), TOL.freeform_fit_mm)
    assert found is not None and found.kind == CYLINDER
    assert found.radius == pytest.approx(7.5, abs=1e-9)
    axis = POSE @ [0, 0, 1]
    assert abs(float(found.direction @ axis)) == pytest.approx(1.0, abs=1e-12)
    off = found.point - SHIFT
    assert np.linalg.norm(off - (off @ axis) * axis) <= 1e-9


def test_cone_is_recovered_with_its_semi_angle_and_radius() -> None:
    slope = math.tan(math.radians(30.0))
    found = fit_primitive(*revolution(12.446, -slope, z0=-3.0, z1=5.5), TOL.freeform_fit_mm)
    assert found is not None and found.kind == CONE
    assert found.semi_angle == pytest.approx(math.radians(30.0), abs=1e-12)
    axis = POSE @ [0, 0, 1]
    assert float(found.direction @ axis) == pytest.approx(-1.0, abs=1e-12)  # radius grows along
    station = float((found.point - SHIFT) @ axis)
    assert found.radius == pytest.approx(12.446 - slope * station, abs=1e-9)


def test_only_estimates_near_the_tolerance_are_refined(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import scipy.optimize

    refined = []
    least_squares = scipy.optimize.least_squares
    monkeypatch.setattr(scipy.optimize, "least_squares",
                        lambda *args, **kwargs: refined.append(1) or least_squares(*args, **kwargs))
    slope = math.tan(math.radians(30.0))
    found = fit_primitive(*revolution(12.446, -slope, z0=-3.0, z1=5.5), TOL.freeform_fit_mm)
    assert found is not None and found.kind == CONE
    # The cylinder's estimate is millimetres off: only the cone's is refined.
    assert len(refined) == 1


def test_sphere_and_near_misses_are_rejected() -> None:
    theta, phi = np.meshgrid(np.linspace(0.3, 1.2, 9), np.linspace(0, 2 * math.pi, 9))
    normals = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                        np.cos(theta)], axis=-1).reshape(-1, 3)
    assert fit_primitive(*placed(20.0 * normals, normals), TOL.freeform_fit_mm) is None
    points, normals = revolution(7.5, 0.0)
    bump = np.zeros(len(points))
    bump[40] = 3.0 * TOL.freeform_fit_mm  # one sample off by three micrometres
    assert fit_primitive(points + bump[:, None] * normals, normals, TOL.freeform_fit_mm) is None
    assert fit_primitive(points + bump[:, None] * normals, normals, 1e-2) is not None


def test_bad_arguments_say_so() -> None:
    points, normals = revolution(7.5, 0.0)
    with pytest.raises(ValueError, match="matching"):
        fit_primitive(points[:5], normals[:5], TOL.freeform_fit_mm)
    with pytest.raises(ValueError, match="matching"):
        fit_primitive(points, normals[:-1], TOL.freeform_fit_mm)
