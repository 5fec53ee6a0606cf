"""Least-squares planes, cylinders and cones through points sampled on a surface, with normals.

OpenCascade's ``GeomConvert_SurfToAnaSurf`` raises on some B-spline cones and cylinders (the
KCL pipe's bevelled ends, for one), which would leave them unrecognised and silently drop their
concentric mates; ``cadio.cad.faces`` then samples the face and fits here. Each fit starts from a
closed-form estimate (the normals of a cylinder or cone all meet its axis and make one angle
with it) and is refined by least squares on the geometric distances, so a sampled exact surface
is recovered to rounding. A fit is accepted only when every sample lies within the caller's
tolerance: a wrong primitive is rejected, never returned.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cadio.records import FloatArray, perpendicular_pair

PLANE, CYLINDER, CONE = "plane", "cylinder", "cone"
# Normals this close to one direction (1 - |cos|) make an axis estimate meaningless.
_SPREAD = 1e-9
# ``fit_primitive`` refines a closed-form estimate only when it lies within this many times
# the tolerance of every sample: the estimate of an exact cylinder or cone is exact to
# rounding (its normal lines meet the axis), and least squares does not bring a primitive
# that is a hundred times off within the tolerance (on the real files no rejected face's
# estimate came within 190 tolerances, nor did its refinement within 190).
_REFINE_WITHIN = 100.0


@dataclass(frozen=True, eq=False)
class FittedSurface:
    """A primitive through the samples.

    direction: (3,) unit: the plane's normal, or the axis (a cone's radius grows along it).
    point: (3,) mm: the samples' centroid (plane), or the axis point at the samples' mean axial
    station. radius: mm at ``point`` (0 for a plane). semi_angle: radians, > 0 for a cone, else
    0. deviation: mm, the largest distance of a sample from the primitive.
    """

    kind: str
    direction: FloatArray
    point: FloatArray
    radius: float
    semi_angle: float
    deviation: float


def fit_primitive(points: FloatArray, normals: FloatArray, tol_mm: float) -> FittedSurface | None:
    """The simplest of plane, cylinder and cone within ``tol_mm`` of every sample.

    Args:
        points: (n, 3) mm, samples of one smooth surface, n >= 7.
        normals: (n, 3) its unit normals at the samples (either orientation, but one for all).
        tol_mm: largest accepted distance of a sample from the primitive.

    Returns:
        The fitted primitive, or None when none of the three fits.

    Raises:
        ValueError: points and normals differ in shape or are too few.
    """
    if points.shape != normals.shape or points.ndim != 2 or len(points) < 7:
        raise ValueError(f"need matching (n >= 7, 3) points and normals, got {points.shape} "
                         f"and {normals.shape}")
    plane = fit_plane(points, normals)
    if plane.deviation <= tol_mm:
        return plane
    for fit in (fit_cylinder, fit_cone):
        found = fit(points, normals, _REFINE_WITHIN * tol_mm)
        if found is not None and found.deviation <= tol_mm:
            return found
    return None


def fit_plane(points: FloatArray, normals: FloatArray) -> FittedSurface:
    """Total least-squares plane through the points (the normals are not needed)."""
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][2]
    deviation = float(np.abs((points - centre) @ normal).max())
    return FittedSurface(PLANE, normal, centre, 0.0, 0.0, deviation)


def fit_cylinder(points: FloatArray, normals: FloatArray, refine_within: float = np.inf
                 ) -> FittedSurface | None:
    """Least-squares cylinder, or None when the normals cannot place an axis.

    Args:
        refine_within: mm; a closed-form estimate that deviates more is returned unrefined.
    """
    axis = _axis_estimate(points, normals)
    if axis is None:
        return None
    d, p = axis
    residuals = _cylinder_residuals(points, d, p)
    params = _refine(residuals, np.array([0.0, 0.0, 0.0, 0.0, _radial(points, p, d).mean()]),
                     refine_within)
    deviation = float(np.abs(residuals(params)).max())
    d, p = _axis_from(params, d, p)
    return FittedSurface(CYLINDER, d, p, float(params[4]), 0.0, deviation)


def fit_cone(points: FloatArray, normals: FloatArray, refine_within: float = np.inf
             ) -> FittedSurface | None:
    """Least-squares cone, or None when the normals cannot place an axis or it is a cylinder.

    Args:
        refine_within: mm; a closed-form estimate that deviates more is returned unrefined.
    """
    axis = _axis_estimate(points, normals)
    if axis is None:
        return None
    d, p = axis
    t = (points - p) @ d
    slope, radius = np.polyfit(t, _radial(points, p, d), 1)
    if slope < 0:  # let the radius grow along the axis: the semi-angle is then positive
        d, slope = -d, -slope
    residuals = _cone_residuals(points, d, p)
    params = _refine(residuals, np.array([0.0, 0.0, 0.0, 0.0, radius, np.arctan(slope)]),
                     refine_within)
    radius, angle = float(params[4]), float(params[5])
    if not 0.0 < angle < 0.5 * np.pi or radius < 0.0:
        return None
    deviation = float(np.abs(residuals(params)).max())
    d, p = _axis_from(params, d, p)
    return FittedSurface(CONE, d, p, radius, angle, deviation)


def _axis_estimate(points: FloatArray, normals: FloatArray) -> tuple[FloatArray, FloatArray] | None:
    """(direction, point) of the line all normal lines meet, as for a cylinder or a cone.

    The normals of a cylinder or cone make one angle with the axis, so their tips lie on a plane
    whose normal is the axis direction; across the axis the normal lines all pass through it.
    The point is placed at the samples' mean axial station, so it moves with them.
    """
    tips = normals - normals.mean(axis=0)
    _, s, vt = np.linalg.svd(tips, full_matrices=False)
    if s[1] ** 2 < _SPREAD * len(normals):
        return None  # the normals are (nearly) one direction: a plane, or a sliver
    d = vt[2]
    across = normals - np.outer(normals @ d, d)
    length = np.linalg.norm(across, axis=1)
    if np.any(length < _SPREAD):
        return None
    m = across / length[:, None]
    project = np.eye(3)[None] - m[:, :, None] * m[:, None, :] - np.outer(d, d)[None]
    x = np.linalg.lstsq(project.sum(axis=0), np.einsum("kij,kj->i", project, points),
                        rcond=None)[0]
    x = x + float((points.mean(axis=0) - x) @ d) * d
    return d, x


def _radial(points: FloatArray, p: FloatArray, d: FloatArray) -> FloatArray:
    """(n,) distances of the points from the line (p, d), mm."""
    rel = points - p
    return np.asarray(np.linalg.norm(rel - np.outer(rel @ d, d), axis=1), dtype=np.float64)


def _axis_from(params: FloatArray, d0: FloatArray, p0: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The axis (d, p) of parameters (tilt 1, tilt 2, shift 1, shift 2, ...) about (d0, p0)."""
    e1, e2 = perpendicular_pair(d0)
    d = d0 + params[0] * e1 + params[1] * e2
    return d / np.linalg.norm(d), p0 + params[2] * e1 + params[3] * e2


def _cylinder_residuals(points: FloatArray, d0: FloatArray, p0: FloatArray
                        ) -> Callable[[FloatArray], FloatArray]:
    """Signed distances from the cylinder of parameters (tilts, shifts, radius)."""
    def residuals(params: FloatArray) -> FloatArray:
        d, p = _axis_from(params, d0, p0)
        out: FloatArray = _radial(points, p, d) - params[4]
        return out

    return residuals


def _cone_residuals(points: FloatArray, d0: FloatArray, p0: FloatArray
                    ) -> Callable[[FloatArray], FloatArray]:
    """Signed distances from the cone of parameters (tilts, shifts, radius at p, semi-angle).

    In the half-plane through the axis and a point the cone is a line; the distance to it is
    the radial excess times the cosine of the semi-angle.
    """
    def residuals(params: FloatArray) -> FloatArray:
        d, p = _axis_from(params, d0, p0)
        t = (points - p) @ d
        excess = _radial(points, p, d) - params[4] - t * np.tan(params[5])
        return np.asarray(excess * np.cos(params[5]), dtype=np.float64)

    return residuals


def _refine(residuals: Callable[[FloatArray], FloatArray], start: FloatArray,
            within: float = np.inf) -> FloatArray:
    """Parameters minimising the squared residuals (Levenberg-Marquardt), from ``start``;
    ``start`` itself where its largest residual exceeds ``within``."""
    if not float(np.abs(residuals(start)).max()) <= within:
        return start
    # Imported here: few faces get this far, and scipy.optimize costs every CAD worker 0.15 s.
    from scipy.optimize import least_squares

    result = least_squares(residuals, start, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return np.asarray(result.x, dtype=np.float64)
