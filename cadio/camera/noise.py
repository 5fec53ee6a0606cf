"""A depth sensor model: noise growing with depth, quantisation, and the holes real cameras leave.

Structured-light and time-of-flight cameras return depth whose error grows with the square of
the distance, store it in millimetre steps, and return nothing at grazing incidence and along
depth discontinuities. ``apply_noise`` turns a clean rendered depth image into such a frame,
reproducibly per (seed, view); colour stays exact.

A stereo camera's error is not independent from pixel to pixel: its matching windows make
neighbouring pixels err together. ``correlated_fraction`` of the depth variance is drawn as a
smooth field (one unit normal per ``correlated_px`` square, interpolated), so that averaging many
pixels does not shrink it as independent noise would (a registration on independent noise alone
would look tens of times better than on a real camera's depth).

``D435``: Intel RealSense D435 at inspection range. Its datasheet's RMS error formula (subpixel
0.08) gives about 0.9 mm at 0.5 m, 1.4 mm at 0.6 m and 3.8 mm at 1 m: sigma = 3.8 mm/m^2 * z^2.
The driver publishes depth in 1 mm steps (16UC1). Half the variance is taken as correlated over
8 px, an assumption (the stereo matching window is 7-9 px); 1% of pixels drop out and edges
lose 2 px. Not modelled: the global depth scale bias of a few percent that one averaged real
measurement showed (980.7 mm read at 1,000 mm), which only a scale fit removes.
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
    # Share of the variance in a smooth field of one unit normal per ``correlated_px`` square
    # (0: independent per pixel): a stereo camera's matching windows make neighbours err together.
    correlated_fraction: float = 0.0
    correlated_px: int = 8

    def depth_sigma_m(self, z_m: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """The standard deviation of a depth read at ``z_m`` (metres): the noise's, and the
        quantisation's step (a uniform error of a twelfth of its square) beside it."""
        noise = self.sigma_base_m + self.sigma_quadratic_per_m * np.asarray(z_m) ** 2
        out: npt.NDArray[np.float64] = np.sqrt(noise ** 2 + self.quantisation_m ** 2 / 12)
        return out


# The inspection camera (module docstring): sigma 3.8 mm/m^2 z^2, 1 mm steps, half correlated.
D435 = NoiseConfig(sigma_base_m=0.0, sigma_quadratic_per_m=0.0038, quantisation_m=0.001,
                   max_incidence_deg=75.0, edge_jump_m=0.01, edge_width_px=2, dropout=0.01,
                   correlated_fraction=0.5, correlated_px=8)


# Compiled loops: one pass with draws for the measured pixels only costs a fraction of numpy's
# passes over the image, and ``measure_depth`` runs without the GIL from start to end, so the
# renderer runs it while open3d casts the next view.
_jit = numba.njit(nogil=True, cache=True)


def sensor_model(noise: NoiseConfig) -> npt.NDArray[np.float32]:
    """``noise`` as ``measure_depth`` takes it: float32 (cos of max incidence, sigma base, sigma
    quadratic, quantisation, dropout, edge jump, edge width, correlated fraction)."""
    return np.array([math.cos(math.radians(noise.max_incidence_deg)), noise.sigma_base_m,
                     noise.sigma_quadratic_per_m, noise.quantisation_m, noise.dropout,
                     noise.edge_jump_m, noise.edge_width_px, noise.correlated_fraction],
                    dtype=np.float32)


def sensor_rng(noise: NoiseConfig, view: int) -> np.random.Generator:
    """The draws of view ``view``: one stream per (seed, view)."""
    return np.random.default_rng([noise.seed, view])


def sensor_field(noise: NoiseConfig, view: int, shape: tuple[int, int]
                 ) -> npt.NDArray[np.float32]:
    """(h, w) float32: the view's smooth unit-variance field (its own stream, so the per-pixel
    draws are those of a model without it); zeros without ``correlated_fraction``."""
    if noise.correlated_fraction <= 0:
        return np.zeros(shape, np.float32)
    rng = np.random.default_rng([noise.seed, view, 1])
    step = max(1, noise.correlated_px)
    coarse = rng.standard_normal((shape[0] // step + 2, shape[1] // step + 2))
    rows, cols = np.arange(shape[0]) / step, np.arange(shape[1]) / step
    r0, c0 = rows.astype(int), cols.astype(int)
    fr, fc = (rows - r0)[:, None], (cols - c0)[None, :]
    corner = {(dr, dc): coarse[np.ix_(r0 + dr, c0 + dc)] for dr in (0, 1) for dc in (0, 1)}
    field = ((1 - fr) * (1 - fc) * corner[0, 0] + fr * (1 - fc) * corner[1, 0]
             + (1 - fr) * fc * corner[0, 1] + fr * fc * corner[1, 1])
    # bilinear blending shrinks the variance (to 4/9 along a line): back to one
    return np.asarray(field / field.std(), dtype=np.float32)


@_jit
def measure_depth(depth: Any, cos_incidence: Any, model: Any, rng: Any, out: Any,
                  field: Any) -> None:
    """``apply_noise`` into ``out`` (h, w) float32, with ``sensor_model``, ``sensor_rng`` and
    ``sensor_field``."""
    edge = _depth_edges(depth, model[5], int(model[6]))
    _measure(depth.reshape(-1), cos_incidence.reshape(-1), edge.reshape(-1), model, rng,
             out.reshape(-1), field.reshape(-1))


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
def _measure(depth: Any, cos_incidence: Any, edge: Any, model: Any, rng: Any, out: Any,
             field: Any) -> None:
    """Per pixel (flat, row-major): 0 where the sensor returns nothing, else a noisy, quantised
    reading (one normal draw, then one uniform draw if there is random dropout; the smooth
    field's share of the variance beside the draw's)."""
    cos_min, base, quadratic, step, dropout = model[0], model[1], model[2], model[3], model[4]
    smooth = np.float32(math.sqrt(model[7]))
    white = np.float32(math.sqrt(1.0 - model[7]))
    for p in range(len(depth)):
        d = depth[p]
        if d <= 0 or cos_incidence[p] < cos_min or edge[p]:
            out[p] = 0
            continue
        n = np.float32(rng.standard_normal())
        if smooth > 0:
            n = white * n + smooth * field[p]
        z = d + n * (quadratic * d * d + base)
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
                  sensor_rng(noise, view), out, sensor_field(noise, view, depth.shape))
    return out
