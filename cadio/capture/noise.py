"""A depth sensor model: noise growing with depth, quantisation, and the holes real cameras leave.

Structured-light and time-of-flight cameras return depth whose error grows with the square of
the distance, store it in millimetre steps, and return nothing at grazing incidence and along
depth discontinuities. ``apply_noise`` turns a clean rendered depth image into such a frame,
reproducibly per (seed, view); colour stays exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True)
class NoiseConfig:
    """Depth sensor model (colour stays exact); draws come from ``seed`` and the view index."""

    seed: int = 0
    # sigma(z) = base + quadratic * z^2 (metres): the z^2 growth of triangulating sensors;
    # 0.5 mm + 1.2 mm/m^2 gives ~3.6 mm at the paper's 1.6 m, like a Kinect-class camera.
    sigma_base_m: float = 0.0005
    sigma_quadratic_per_m: float = 0.0012
    quantisation_m: float = 0.001  # 1 mm depth steps, as 16-bit millimetre images store
    max_incidence_deg: float = 75.0  # surfaces seen more obliquely return no depth
    edge_jump_m: float = 0.02  # a neighbour this much nearer/farther marks a discontinuity
    edge_width_px: int = 1  # pixels dropped on each side of a discontinuity
    dropout: float = 0.0  # extra fraction of pixels missing at random



def _depth_edges(depth: npt.NDArray[np.float32], jump_m: float,
                 width_px: int) -> npt.NDArray[np.bool_]:
    """Pixels next to a depth discontinuity (a jump > ``jump_m`` or a hit/miss boundary)."""
    z = np.where(depth > 0, depth, np.float32(1e6))  # a miss is a far surface: hit/miss = jump
    edge = np.zeros(depth.shape, dtype=bool)
    for axis in (0, 1):
        a = np.moveaxis(z, axis, 0)
        jump = np.abs(a[1:] - a[:-1]) > jump_m
        e = np.moveaxis(edge, axis, 0)
        e[1:] |= jump
        e[:-1] |= jump
    if width_px > 1:
        from scipy.ndimage import binary_dilation

        edge = binary_dilation(edge, iterations=width_px - 1)
    return edge


def apply_noise(depth: npt.NDArray[np.float32], cos_incidence: npt.NDArray[np.float32],
                noise: NoiseConfig, view: int) -> npt.NDArray[np.float32]:
    """Sensor model on a clean depth image.

    Args:
        depth: (h, w) float32 metres, 0 where missing.
        cos_incidence: (h, w) |cos| of the angle between ray and surface normal.
        noise: the model; draws are seeded by (noise.seed, view).
        view: view index, so each view gets its own reproducible noise.
    Returns:
        (h, w) float32 metres, 0 where the sensor returns nothing.
    """
    rng = np.random.default_rng([noise.seed, view])
    f32 = np.float32
    sigma = f32(noise.sigma_base_m) + f32(noise.sigma_quadratic_per_m) * depth * depth
    z = depth + rng.standard_normal(depth.shape, dtype=f32) * sigma  # float32: ~0.1 um steps
    if noise.quantisation_m > 0:
        z = np.round(z * f32(1 / noise.quantisation_m)) * f32(noise.quantisation_m)
    keep = (depth > 0) & (z > 0)
    keep &= cos_incidence >= math.cos(math.radians(noise.max_incidence_deg))
    keep &= ~_depth_edges(depth, noise.edge_jump_m, noise.edge_width_px)
    if noise.dropout > 0:
        keep &= rng.random(depth.shape, dtype=f32) >= noise.dropout
    return np.where(keep, z, f32(0))
