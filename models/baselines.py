"""Learned completion baselines beside the paper's network: 3D-R2N2 (Choy et al. 2016).

3D-R2N2 encodes each 2D view with a 2D CNN into a feature vector, feeds the vectors in turn to a
3D convolutional LSTM over a coarse 4^3 grid, and decodes the last hidden state with 3D
transposed convolutions. Here the 2D view is the contract's ``depth`` image (distance along +y
and an observed mask, both in the grid frame), and the decoder reaches the same n_out grid as
the paper's generator, so the two are scored alike. The `ae` baseline is
``CompletionConfig(lstm=False, gan=False)`` in ``models.completion``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise

from torch import Tensor, nn

from models.completion import BaseConfig, ConvLSTM3d, check_shape, to_logits


@dataclass(frozen=True)
class R2N2Config(BaseConfig):
    """3D-R2N2 at this project's grids; training fields as for every method (``BaseConfig``)."""

    grid: int = 4  # side of the recurrent 3D grid (3D-R2N2's 4^3)
    hidden: int = 64  # channels of each recurrent cell: the generator's bottleneck width at 32^3
    feature: int = 256  # per-view vector from the 2D encoder (3D-R2N2: 1024 for 127^2 images)
    grid_in: int = 8  # channels the feature vector is unfolded into on the grid, per cell

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.n_out % self.grid or self.grid & (self.grid - 1) or self.depth_side <= self.grid:
            raise ValueError(f"grid {self.grid} must be a power of two below n_out and 2 n_in")

    @property
    def method(self) -> str:
        return "r2n2"

    @property
    def depth_side(self) -> int:
        """Side d of the contract's depth images: 2 n_in."""
        return 2 * self.n_in


class DepthEncoder(nn.Module):
    """2D convolutions from the (2, d, d) depth view down to the grid side, then a vector."""

    def __init__(self, cfg: R2N2Config) -> None:
        super().__init__()
        levels = int(math.log2(cfg.depth_side // cfg.grid))
        chans = [2] + [cfg.width * 2 ** min(k, 2) for k in range(levels)]
        self.convs = nn.Sequential(*(
            nn.Sequential(nn.Conv2d(a, b, 4, 2, 1), nn.LeakyReLU(0.2)) for a, b in pairwise(chans)
        ))
        self.fc = nn.Sequential(nn.Flatten(), nn.Linear(chans[-1] * cfg.grid**2, cfg.feature),
                                nn.LeakyReLU(0.2))

    def forward(self, x: Tensor) -> Tensor:
        """x (N, 2, d, d) -> (N, feature)."""
        return self.fc(self.convs(x))


class R2N2(nn.Module):
    """Depth views (B, V, 2, d, d) -> logits (B, 1, n_out^3) through a 4^3 conv-LSTM."""

    input_key = "depth"  # the data contract's field this model reads

    def __init__(self, cfg: R2N2Config) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = DepthEncoder(cfg)
        self.to_grid = nn.Linear(cfg.feature, cfg.grid_in * cfg.grid**3)
        self.lstm = ConvLSTM3d(cfg.grid_in, cfg.hidden)
        doublings = int(math.log2(cfg.n_out // cfg.grid))
        self.decoder = to_logits(cfg.hidden, doublings, max(cfg.width // 2, 4))

    def forward(self, depth: Tensor) -> Tensor:
        """depth (B, V, 2, d, d) float, d = 2 n_in -> (B, 1, n_out, n_out, n_out) logits.

        Raises:
            ValueError: depth does not have that shape.
        """
        d, g = self.cfg.depth_side, self.cfg.grid
        check_shape(depth, "depth", (2, d, d))
        b, v = depth.shape[:2]
        x = depth.to(next(self.parameters()).dtype).reshape(b * v, 2, d, d)
        cells = self.to_grid(self.encoder(x)).view(b, v, -1, g, g, g)  # (B, V, C, g, g, g)
        state = None
        for t in range(v):
            state = self.lstm(cells[:, t], state)  # (B, H, g, g, g)
        assert state is not None
        return self.decoder(state[0])  # (B, 1, n_out, n_out, n_out)
