"""What a registration's points constrain: the pose's covariance and its unobservable directions.

The point-to-plane Hessian of a fit (``register.Fit.hessian``: J^T J over its inliers, a turn
about the part's centroid then a shift) says how much the points resist each small motion of
the part. A direction they hardly resist is not observable from the view: a shaft turned about
its axis, a plate slid in its plane where no edge was seen. ``pose_uncertainty`` splits the six
directions into observable ones, with their standard deviation, and the others; a deviation
along an unobservable direction is "not observable", never a pass.

The covariance is the fit's residual variance over the Hessian, inflated by the number of
points that err together: a stereo camera's pixels are not independent (its matching windows;
``cadio.camera.noise``), so n points carry about n / ``correlated_points`` independent ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cadio.records import FloatArray

# An eigen-direction the points resist with less than this share of the strongest (in units
# where a turn counts by its motion at the part's rim) is not observable.
MIN_SHARE = 1e-3


@dataclass(frozen=True)
class PoseUncertainty:
    """A pose's covariance in the observable directions, and the unobservable ones.

    centre: (3,) the point the turns are about (world mm); radius_mm: the scale of turns.
    covariance: (6, 6) over (turn rad, shift mm), infinite nowhere: the unobservable directions
    are left out of it and listed in ``unobservable`` (6-vectors in the same units).
    """

    centre: FloatArray
    radius_mm: float
    covariance: FloatArray
    unobservable: FloatArray

    def sigma_along(self, direction: FloatArray) -> float:
        """Standard deviation of ``direction`` . (turn, shift); inf where it reaches an
        unobservable direction (more than a tenth of it along one)."""
        d = np.asarray(direction, dtype=np.float64)
        norm = self._scaled_norm(d)
        for u in self.unobservable:
            if abs(float(self._scale(d) @ u)) > 0.1 * norm:
                return math.inf
        return math.sqrt(max(float(d @ self.covariance @ d), 0.0))

    def shift_sigma_mm(self) -> float:
        """The standard deviation of the part's shift in its least held observable direction
        (an upper bound on any one direction's); inf where the covariance is not finite (a fit
        without inliers)."""
        shift = self.covariance[3:, 3:]
        if not np.all(np.isfinite(shift)):
            return math.inf
        return math.sqrt(max(float(np.linalg.eigvalsh(shift).max()), 0.0))

    def turn_sigma_deg(self) -> float:
        """The standard deviation of the part's turn about its least held observable axis,
        degrees (a turn the view cannot see, a revolved part's roll, moves none of its faces'
        directions); inf where the covariance is not finite."""
        turn = self.covariance[:3, :3]
        if not np.all(np.isfinite(turn)):
            return math.inf
        return math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(turn).max()), 0.0)))

    def _scale(self, d: FloatArray) -> FloatArray:
        out: FloatArray = d * np.array([1 / self.radius_mm] * 3 + [1.0] * 3)
        return out

    def _scaled_norm(self, d: FloatArray) -> float:
        return float(np.linalg.norm(self._scale(d))) or 1e-12


def pose_uncertainty(hessian: FloatArray, rmse_mm: float, inliers: int, centre: FloatArray,
                     radius_mm: float, correlated_points: float = 16.0) -> PoseUncertainty:
    """The pose's uncertainty from a fit's Hessian and residual.

    Args:
        hessian: (6, 6) J^T J of the fit (turn rad about ``centre``, shift mm).
        rmse_mm: the inliers' point-to-plane RMS; inliers: their number.
        radius_mm: the part's scale for turns (half its diameter).
        correlated_points: points per independent error (``cadio.camera.noise``'s correlated
            field: about its correlation cell's pixels at inspection range).
    """
    # turns in millimetres at the rim: (turn, shift) = S (turn', shift'), S = diag(1/r, 1)
    scale = np.array([1 / radius_mm] * 3 + [1.0] * 3)
    h = np.asarray(hessian, dtype=np.float64) * np.outer(scale, scale)
    values, vectors = np.linalg.eigh(h)
    top = max(float(values.max()), 1e-12)
    keep = values > MIN_SHARE * top
    variance = max(rmse_mm, 1e-3) ** 2 * max(1.0, correlated_points if inliers > 0 else 1.0)
    inverse = (vectors[:, keep] / values[keep]) @ vectors[:, keep].T * variance
    cov = inverse * np.outer(scale, scale)
    return PoseUncertainty(np.asarray(centre, dtype=np.float64), radius_mm, cov,
                           vectors[:, ~keep].T.copy())


def point_motion(point: FloatArray, centre: FloatArray) -> FloatArray:
    """(3, 6): how a point moves under a small (turn, shift) of the part about ``centre``."""
    r = np.asarray(point, dtype=np.float64) - centre
    cross = np.array([[0, r[2], -r[1]], [-r[2], 0, r[0]], [r[1], -r[0], 0]])
    return np.hstack([cross, np.eye(3)])


def small_motion(delta: FloatArray, centre: FloatArray) -> FloatArray:
    """(4, 4): rotation ``delta[:3]`` (axis-angle) about ``centre``, then ``delta[3:]``
    (the small motions of ``pose_uncertainty``'s covariance, composed)."""
    out: FloatArray = small_motions(np.asarray(delta, dtype=np.float64)[None], centre)[0]
    return out


def small_motions(delta: FloatArray, centre: FloatArray) -> FloatArray:
    """(k, 4, 4): ``small_motion`` of each row of ``delta`` (k, 6), about one centre."""
    theta = np.linalg.norm(delta[:, :3], axis=1)
    still = theta < 1e-12
    k = delta[:, :3] / np.where(still, 1.0, theta)[:, None]
    kx = np.zeros((len(delta), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx[:, 1, 0], kx[:, 2, 0], kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    rot = np.eye(3) + np.sin(theta)[:, None, None] * kx \
        + (1 - np.cos(theta))[:, None, None] * (kx @ kx)
    rot[still] = np.eye(3)
    out = np.tile(np.eye(4), (len(delta), 1, 1))
    out[:, :3, :3] = rot
    out[:, :3, 3] = centre - rot @ np.asarray(centre, dtype=np.float64) + delta[:, 3:]
    return out
