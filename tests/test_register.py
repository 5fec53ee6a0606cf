"""Tests of cadio.capture.register: ICP recovers a known rigid motion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cadio.capture.register import register


def _box_surface(n: int = 4000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, (n, 3)) * [0.06, 0.04, 0.03]
    face = rng.integers(0, 3, n)
    sign = rng.choice([-1.0, 1.0], n)
    half = np.array([0.06, 0.04, 0.03])
    pts[np.arange(n), face] = sign * half[face]
    return pts


def _motion(deg: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    m = np.eye(4)
    m[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    m[:3, 3] = t
    return m


def test_icp_recovers_a_known_rigid_motion() -> None:
    surface = _box_surface()
    motion = _motion(3.0, (0.004, -0.002, 0.001))
    completion = surface @ motion[:3, :3].T + motion[:3, 3]  # the completion is off the scan
    scan = _box_surface(1500, seed=1)
    scan = scan[scan[:, 1] <= -0.0399]  # the camera saw one face only...
    scan = np.vstack([scan, _box_surface(1500, seed=2)[:600]])  # ...and some of the others
    result = register(completion, scan, max_distance=0.02)
    error = result.transform @ motion  # identity when the motion is undone exactly
    angle = math.degrees(math.acos(min(1.0, (np.trace(error[:3, :3]) - 1) / 2)))
    assert angle < 0.5 and np.linalg.norm(error[:3, 3]) < 1e-3  # 3 degrees, 4.6 mm before
    assert result.fitness > 0.95 and result.residual < 2e-3


def test_registration_of_a_perfect_completion_is_the_identity() -> None:
    surface = _box_surface()
    result = register(surface, surface[::3], max_distance=0.01)
    assert result.transform == pytest.approx(np.eye(4), abs=1e-9)
    assert result.residual == pytest.approx(0.0, abs=1e-9)


def test_registration_needs_points() -> None:
    with pytest.raises(ValueError, match="points on both sides"):
        register(np.zeros((0, 3)), np.ones((3, 3)), 0.1)
