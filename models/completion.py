"""Shape completion: the paper's "3D composition network", a 3D GAN with 3D conv-LSTM units.

The generator (3D-RecGAN++'s shape) encodes each view's observed occupancy grid with 3D
convolutions, merges the views with a 3D convolutional LSTM at the coarse bottleneck (so a
sequence of views refines one estimate, and a single view works on its own), and decodes with
skip connections to a finer output grid of logits. A conditional critic of six 3D convolutions
scores (observed input, solid) pairs for a WGAN-GP loss. The `ae` baseline is the same generator
with ``lstm=False`` and ``gan=False``. No I/O here: training lives in ``models.train``.

Grids are (x, y, z) = (right, away from the first view's camera, up); every view of one example
is expressed in one grid, so views can be merged voxel by voxel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise

import torch
import torch.nn.functional as F
from torch import Tensor, nn


@dataclass(frozen=True)
class BaseConfig:
    """What every learned completion method shares: grids, width, loss, optimiser, schedule."""

    n_in: int = 32  # input grid side (64 in the paper); a power of two
    n_out: int = 64  # output grid side (256 in the paper); n_in times a power of two
    width: int = 16  # channels of the finest encoder level, doubling per level
    seed: int = 0  # torch, numpy and python seeds; also keys batch and view sampling
    batch_size: int = 8
    max_views: int = 8  # training sequences hold 1..max_views views (the contract's upper bound)
    eval_views: int = 1  # leading views seen at validation: the paper's single-scan protocol
    eval_every: int = 100  # steps per "epoch": validation IoU, best checkpoint, resumable snapshot
    # Voxel cross-entropy weights (3D-RecGAN++): a missed solid voxel costs 0.85/0.15 = 5.7 times
    # a false fill, because solids fill a few percent of the grid and a plain loss empties it.
    w_occupied: float = 0.85
    w_empty: float = 0.15
    lr: float = 1e-4  # Adam, generator (the paper's)
    # Training inputs lose up to this share of their seen-surface voxels (``training_batch``).
    surface_dropout: float = 0.3
    # Share of training examples mirrored across the observer's right axis, views and truth
    # alike (``training_batch``): a mirrored part seen by a mirrored camera is as real a view.
    mirror: float = 0.0

    def __post_init__(self) -> None:
        if self.n_in < 8 or self.n_in & (self.n_in - 1):
            raise ValueError(f"n_in must be a power of two >= 8, got {self.n_in}")
        ratio = self.n_out // self.n_in
        if self.n_out % self.n_in or ratio & (ratio - 1):
            raise ValueError(f"n_out must be n_in times a power of two, got {self.n_out}")
        if self.width < 2 or self.batch_size < 1 or self.eval_every < 1:
            raise ValueError("width >= 2, batch_size >= 1 and eval_every >= 1 are required")
        if not 1 <= self.eval_views <= self.max_views <= 8:
            raise ValueError("need 1 <= eval_views <= max_views <= 8 (the data contract's V)")
        if min(self.w_occupied, self.w_empty, self.lr) <= 0:
            raise ValueError("loss weights and learning rate must be positive")
        if not 0 <= self.surface_dropout < 1:
            raise ValueError(f"surface_dropout must be in [0, 1), got {self.surface_dropout}")
        if not 0 <= self.mirror <= 1:
            raise ValueError(f"mirror must be in [0, 1], got {self.mirror}")


@dataclass(frozen=True)
class CompletionConfig(BaseConfig):
    """The generator, its critic and their losses; ``method`` names the variant."""

    lstm: bool = True  # merge views with the bottleneck conv-LSTM (False: union of the views)
    gan: bool = True  # add the conditional WGAN-GP critic to the cross-entropy
    bottleneck: int = 4  # side of the coarsest grid, where the LSTM runs (3D-R2N2's 4^3)
    critic_width: int = 8  # channels of the critic's first convolution, doubling to 8x
    gp_lambda: float = 10.0  # WGAN-GP penalty weight (Gulrajani et al.)
    # The penalty keeps the critic's gradient over the whole grid near norm 1, while the mean
    # cross-entropy's gradient has norm ~1/sqrt(n_out^3) (2e-3 at 64^3): 1e-3 keeps the
    # adversarial term a sharpening regulariser rather than the main signal.
    adv_weight: float = 1e-3
    lr_d: float = 5e-5  # Adam, critic (the paper's)
    # Critic updates per generator update, on the same batch. WGAN-GP's 5 would make a CPU step
    # several times slower; the cross-entropy carries the learning here.
    critic_steps: int = 1
    # The penalty on every gp_every-th critic update only, weighted by gp_every (StyleGAN2's
    # lazy regularisation): its double backward costs about three critic updates on a CPU.
    gp_every: int = 4

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.n_in // self.bottleneck < 2 or self.n_in % self.bottleneck:
            raise ValueError(f"bottleneck {self.bottleneck} must divide n_in / 2 ({self.n_in})")
        if self.gan and (self.n_out < 32 or self.critic_steps < 1 or self.gp_every < 1):
            raise ValueError("the critic needs n_out >= 32, critic_steps >= 1, gp_every >= 1")

    @property
    def critic_n(self) -> int:
        """Side of the grid the critic judges: the input grid, 32 at least, n_out at most."""
        return min(self.n_out, max(self.n_in, 32))

    @property
    def method(self) -> str:
        """``gan_lstm`` (the paper), ``ae`` (neither), or the ablations ``gan`` and ``lstm``."""
        if self.gan and self.lstm:
            return "gan_lstm"
        return "gan" if self.gan else "lstm" if self.lstm else "ae"

    @property
    def levels(self) -> int:
        """Stride-2 encoder levels from n_in down to the bottleneck."""
        return int(math.log2(self.n_in // self.bottleneck))


def check_shape(x: Tensor, name: str, trailing: tuple[int, ...]) -> None:
    """Raise ValueError unless ``x`` is (B, V, *trailing) with B, V >= 1."""
    if x.dim() != 2 + len(trailing) or tuple(x.shape[2:]) != trailing or 0 in x.shape[:2]:
        want = ", ".join(["B", "V", *map(str, trailing)])
        raise ValueError(f"{name} must have shape ({want}); got {tuple(x.shape)}")


def down3d(c_in: int, c_out: int) -> nn.Sequential:
    """Halve the grid: 4^3 convolution, stride 2, leaky ReLU (3D-RecGAN++'s encoder block)."""
    return nn.Sequential(nn.Conv3d(c_in, c_out, 4, 2, 1), nn.LeakyReLU(0.2))


def up3d(c_in: int, c_out: int) -> nn.Sequential:
    """Double the grid: 4^3 transposed convolution, stride 2, ReLU."""
    return nn.Sequential(nn.ConvTranspose3d(c_in, c_out, 4, 2, 1), nn.ReLU())


def to_logits(c_in: int, doublings: int, c_min: int) -> nn.Sequential:
    """Up blocks halving channels (not below ``c_min``), the last one straight to 1 logit.

    No convolution runs at the output grid with more than one output channel: on a CPU a
    3^3 convolution's backward over 64^3 x 8 samples costs seconds, a transposed one to a
    single channel a fraction of that. With no doubling, a 3^3 convolution makes the logits.
    """
    if doublings == 0:
        return nn.Sequential(nn.Conv3d(c_in, 1, 3, padding=1))
    blocks = []
    for _ in range(doublings - 1):
        c_out = max(c_in // 2, c_min)
        blocks.append(up3d(c_in, c_out))
        c_in = c_out
    return nn.Sequential(*blocks, nn.ConvTranspose3d(c_in, 1, 4, 2, 1))


class ConvLSTM3d(nn.Module):
    """A 3D convolutional LSTM cell (3D-R2N2): gates are convolutions over [input, hidden]."""

    def __init__(self, c_in: int, hidden: int, kernel: int = 3) -> None:
        super().__init__()
        self.hidden = hidden
        self.gates = nn.Conv3d(c_in + hidden, 4 * hidden, kernel, padding=kernel // 2)

    def forward(self, x: Tensor, state: tuple[Tensor, Tensor] | None) -> tuple[Tensor, Tensor]:
        """One step: x (B, C, G, G, G), state (h, c) or None -> new (h, c), each (B, H, G, G, G)."""
        if state is None:
            zeros = x.new_zeros(x.shape[0], self.hidden, *x.shape[2:])
            state = (zeros, zeros)
        h, c = state
        i, f, o, g = self.gates(torch.cat([x, h], 1)).chunk(4, 1)  # (B, H, G, G, G) each
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        return torch.sigmoid(o) * torch.tanh(c), c


STATES = 2  # channels of a view's input grid: seen surface, seen free


def union_views(views: Tensor) -> Tensor:
    """(B, V, 2, n^3) state grids -> (B, 1, 2, n^3): surface where any view saw the part's
    surface, free where any view saw through and none saw surface (``observe.union_states``)."""
    surface = views[:, :, 0].amax(1)
    free = views[:, :, 1].amax(1) * (1 - surface)
    return torch.stack([surface, free], 1)[:, None]


class Encoder(nn.Module):
    """Stride-2 3D convolutions from n_in to the bottleneck; returns every level's features."""

    def __init__(self, width: int, levels: int) -> None:
        super().__init__()
        chans = [STATES] + [width * 2**k for k in range(levels)]
        self.blocks = nn.ModuleList(down3d(a, b) for a, b in pairwise(chans))

    def forward(self, x: Tensor) -> list[Tensor]:
        """x (N, 2, n, n, n) -> [x, (N, w, n/2, ...), ..., (N, w 2^(L-1), n/2^L, ...)]."""
        feats = [x]
        for block in self.blocks:
            feats.append(block(feats[-1]))
        return feats


class Decoder(nn.Module):
    """Up blocks from the bottleneck joined with the encoder's skips, then on to n_out."""

    def __init__(self, cfg: CompletionConfig) -> None:
        super().__init__()
        w, levels = cfg.width, cfg.levels
        skip_ch = [STATES] + [w * 2**k for k in range(levels - 1)]  # skips at sides n, n/2, ...
        c_in = w * 2 ** (levels - 1)
        self.ups = nn.ModuleList()
        for k in reversed(range(levels)):
            c_out = skip_ch[k] if k else max(w // 2, 4)
            self.ups.append(up3d(c_in, c_out))
            c_in = c_out + skip_ch[k]
        self.head = to_logits(c_in, int(math.log2(cfg.n_out // cfg.n_in)), 4)

    def forward(self, x: Tensor, skips: list[Tensor]) -> Tensor:
        """x (B, C, b, b, b), skips finest first -> logits (B, 1, n_out, n_out, n_out)."""
        for up, skip in zip(self.ups, reversed(skips), strict=True):
            x = torch.cat([up(x), skip], 1)  # (B, C' + C_skip, 2s, 2s, 2s)
        return self.head(x)  # (B, 1, n_out, n_out, n_out)


class Generator(nn.Module):
    """State grids of V views -> logits of the completed solid."""

    input_key = "inputs"  # the data contract's field this model reads

    def __init__(self, cfg: CompletionConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg.width, cfg.levels)
        hidden = cfg.width * 2 ** (cfg.levels - 1)
        self.lstm = ConvLSTM3d(hidden, hidden) if cfg.lstm else None
        self.decoder = Decoder(cfg)

    def forward(self, views: Tensor) -> Tensor:
        """views (B, V, 2, n_in, n_in, n_in), any dtype, channel 0 seen surface, 1 seen free
        -> (B, 1, n_out^3) logits.

        Raises:
            ValueError: views do not have that shape.
        """
        n = self.cfg.n_in
        check_shape(views, "views", (STATES, n, n, n))
        x = views.to(next(self.parameters()).dtype)
        if self.lstm is None:
            # Without a recurrent unit the views merge where they can: all share one grid, so
            # their union is itself a valid (fuller) observation.
            x = union_views(x)  # (B, 1, 2, n, n, n)
        b, v = x.shape[:2]
        feats = self.encoder(x.reshape(b * v, STATES, n, n, n))  # views batched through
        per_view = [f.unflatten(0, (b, v)) for f in feats]  # (B, V, C, s, s, s) each
        # Skips merge by a max over views: order-free, equal to the lone view's features when
        # V = 1 (so one view and many views feed the decoder the same kind of evidence), and a
        # "seen by any view" union at the finest level, where the skip is the occupancy itself.
        # A mean would dilute what one view alone saw; the last view alone would drop the fine
        # detail of earlier views that the coarse LSTM state cannot carry.
        skips = [f.amax(1) for f in per_view[:-1]]  # (B, C, s, s, s), finest first
        if self.lstm is None:
            return self.decoder(per_view[-1][:, 0], skips)
        state = None
        for t in range(v):  # the sequence refines one estimate, view by view
            state = self.lstm(per_view[-1][:, t], state)  # (B, H, b, b, b)
        assert state is not None
        return self.decoder(state[0], skips)


class Critic(nn.Module):
    """Conditional WGAN-GP critic: six 3D convolutions on (input, solid) -> score.

    The paper's discriminator ends in a sigmoid; a Wasserstein critic must be an unbounded
    1-Lipschitz score, so the sigmoid is dropped (and there is no normalisation layer, which
    would break the per-sample gradient penalty). It judges at ``CompletionConfig.critic_n``
    (the input grid, 32 at least): the solid is average-pooled to it and the input upsampled
    to it. At 64^3 a critic on the full output grid cost two thirds of a CPU training step
    (2.5 s, its gradient penalty alone 1.3 s every fourth step); the voxel loss already judges
    every output voxel, the critic the shape's plausibility, which a coarser grid shows.
    """

    def __init__(self, cfg: CompletionConfig) -> None:
        super().__init__()
        self.up = cfg.critic_n // cfg.n_in
        self.down = cfg.n_out // cfg.critic_n
        chans = [STATES + 1] + [cfg.critic_width * 2 ** min(k, 3) for k in range(5)]
        self.convs = nn.Sequential(*(down3d(a, b) for a, b in pairwise(chans)))
        self.score = nn.Conv3d(chans[-1], 1, cfg.critic_n // 32)  # the sixth: a cube -> 1

    def forward(self, observed: Tensor, solid: Tensor) -> Tensor:
        """observed (B, 2, n_in^3) union of the views' states, solid (B, 1, n_out^3) in [0, 1]
        -> (B,)."""
        cond = F.interpolate(observed, scale_factor=self.up, mode="nearest") if self.up > 1 \
            else observed  # (B, 2, c^3)
        shape = F.avg_pool3d(solid, self.down) if self.down > 1 else solid  # (B, 1, c^3)
        x = self.convs(torch.cat([cond, shape], 1))  # (B, 8 cw, c/32, ...)
        return self.score(x).flatten()  # (B,)


def voxel_loss(logits: Tensor, target: Tensor, w_occupied: float, w_empty: float) -> Tensor:
    """Weighted voxel cross-entropy, mean over voxels and batch (from logits, for stability).

    Args:
        logits: (B, 1, n, n, n) before the sigmoid.
        target: (B, 1, n, n, n) 1 = solid, 0 = empty.
    """
    return -(w_occupied * target * F.logsigmoid(logits)
             + w_empty * (1 - target) * F.logsigmoid(-logits)).mean()


def gradient_penalty(critic: Critic, observed: Tensor, real: Tensor, fake: Tensor,
                     eps: Tensor) -> Tensor:
    """WGAN-GP: mean of (|grad of the score at a random mix of real and fake| - 1)^2.

    Args:
        observed: (B, 2, n_in^3) the critic's condition.
        real, fake: (B, 1, n_out^3) truth and generated probabilities (detached).
        eps: (B,) mixing weights in [0, 1], drawn by the caller (so it controls the seed).
    """
    mix = (eps.view(-1, 1, 1, 1, 1) * real + (1 - eps.view(-1, 1, 1, 1, 1)) * fake)
    mix.requires_grad_(True)
    (grad,) = torch.autograd.grad(critic(observed, mix).sum(), mix, create_graph=True)
    return ((grad.flatten(1).norm(dim=1) - 1) ** 2).mean()
