"""A depth sensor model: noise growing with depth, quantisation, and the holes real cameras leave.

Structured-light and time-of-flight cameras return depth whose error grows with the square of
the distance, store it in millimetre steps, and return nothing at grazing incidence and along
depth discontinuities. ``apply_noise`` turns a clean rendered depth image into such a frame,
reproducibly per (seed, view); colour stays exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numba
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


# Compiled loops: one pass with draws for the measured pixels only costs a fraction of numpy's
# passes over the image, and ``measure_depth`` runs without the GIL from start to end, so the
# renderer runs it while open3d casts the next view.
_jit = numba.njit(nogil=True, cache=True)


def sensor_model(noise: NoiseConfig) -> npt.NDArray[np.float32]:
    """``noise`` as ``measure_depth`` takes it: float32 (cos of max incidence, sigma base, sigma
    quadratic, quantisation, dropout, edge jump, edge width)."""
    return np.array([math.cos(math.radians(noise.max_incidence_deg)), noise.sigma_base_m,
                     noise.sigma_quadratic_per_m, noise.quantisation_m, noise.dropout,
                     noise.edge_jump_m, noise.edge_width_px], dtype=np.float32)


def sensor_rng(noise: NoiseConfig, view: int) -> np.random.Generator:
    """The draws of view ``view``: one stream per (seed, view)."""
    return np.random.default_rng([noise.seed, view])


@_jit
def measure_depth(depth: Any, cos_incidence: Any, model: Any, rng: Any, out: Any) -> None:
    """``apply_noise`` into ``out`` (h, w) float32, with ``sensor_model`` and ``sensor_rng``."""
    edge = _depth_edges(depth, model[5], int(model[6]))
    _measure(depth.reshape(-1), cos_incidence.reshape(-1), edge.reshape(-1), model, rng,
             out.reshape(-1))


@_jit
def _depth_edges(depth: Any, jump_m: Any, width_px: int) -> Any:
    """Pixels within ``width_px`` of a depth discontinuity (a jump > ``jump_m`` or a hit/miss
    boundary), as (h, w) bool."""
    edge = np.empty(depth.shape, dtype=np.bool_)
    _mark_edges(depth, jump_m, edge)
    for _ in range(width_px - 1):
        edge = _dilate(edge)
    return edge


@_jit
def _mark_edges(depth: Any, jump_m: Any, edge: Any) -> None:
    """edge[r, c]: the depth jumps by more than ``jump_m`` to one of the 4 neighbours; a miss
    (0) counts as a far surface, so hit/miss boundaries are jumps too. Each pixel reads its
    neighbours and writes once: twice as fast as marking both sides of each jump."""
    h, w = depth.shape
    for r in range(h):
        for c in range(w):
            z = _far_if_missing(depth[r, c])
            e = c > 0 and abs(z - _far_if_missing(depth[r, c - 1])) > jump_m
            e |= c + 1 < w and abs(z - _far_if_missing(depth[r, c + 1])) > jump_m
            e |= r > 0 and abs(z - _far_if_missing(depth[r - 1, c])) > jump_m
            e |= r + 1 < h and abs(z - _far_if_missing(depth[r + 1, c])) > jump_m
            edge[r, c] = e


@_jit
def _far_if_missing(z: Any) -> Any:
    return z if z > 0 else np.float32(1e6)


@_jit
def _dilate(mask: Any) -> Any:
    """One step of binary dilation by the 4-neighbour cross (scipy.ndimage's default)."""
    h, w = mask.shape
    out = np.empty_like(mask)
    for r in range(h):
        for c in range(w):
            out[r, c] = (mask[r, c] or (c > 0 and mask[r, c - 1]) or (c + 1 < w and mask[r, c + 1])
                         or (r > 0 and mask[r - 1, c]) or (r + 1 < h and mask[r + 1, c]))
    return out


@_jit
def _measure(depth: Any, cos_incidence: Any, edge: Any, model: Any, rng: Any, out: Any) -> None:
    """Per pixel (flat, row-major): 0 where the sensor returns nothing, else a noisy, quantised
    reading (one normal draw, then one uniform draw if there is random dropout)."""
    cos_min, base, quadratic, step, dropout = model[0], model[1], model[2], model[3], model[4]
    for p in range(len(depth)):
        d = depth[p]
        if d <= 0 or cos_incidence[p] < cos_min or edge[p]:
            out[p] = 0
            continue
        z = d + np.float32(rng.standard_normal()) * (quadratic * d * d + base)
        if step > 0:
            z = np.float32(np.rint(z / step)) * step
        if dropout > 0 and rng.random() < dropout:
            z = np.float32(0)
        out[p] = max(z, np.float32(0))


def apply_noise(depth: npt.NDArray[np.float32], cos_incidence: npt.NDArray[np.float32],
                noise: NoiseConfig, view: int) -> npt.NDArray[np.float32]:
    """Sensor model on a clean depth image.

    Random numbers are drawn only for the pixels the sensor measures, in row-major order: one
    standard normal each, independent per pixel and per view.

    Args:
        depth: (h, w) float32 metres, 0 where missing.
        cos_incidence: (h, w) |cos| of the angle between ray and surface normal.
        noise: the model; draws are seeded by (noise.seed, view).
        view: view index, so each view gets its own reproducible noise.
    Returns:
        (h, w) float32 metres, 0 where the sensor returns nothing.
    """
    out = np.empty(depth.shape, dtype=np.float32)
    measure_depth(np.ascontiguousarray(depth, dtype=np.float32),
                  np.ascontiguousarray(cos_incidence, dtype=np.float32), sensor_model(noise),
                  sensor_rng(noise, view), out)
    return out
