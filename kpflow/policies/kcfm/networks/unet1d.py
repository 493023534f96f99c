"""A small 1-D temporal U-Net for action chunks: Diffusion Policy's ``ConditionalUnet1D`` (Chi et al. 2023), made
small enough to run a 10-step flow in a few milliseconds on one CPU thread.

The network maps a chunk ``x [B, H, A]``, a scalar flow time ``t [B]`` and a condition ``c [B, C]`` to a velocity
``[B, H, A]``; built with ``n_times=2`` it takes an interval ``t [B, 2] = (s, t)`` instead (an average velocity,
:mod:`~kpflow.policies.kcfm.objectives.meanflow`), embedded as ``emb(s) + emb'(t - s)``. Convolutions run over the time axis ``H`` with the ``A`` action dimensions as input channels. Every
residual block is FiLM-conditioned on ``[emb(t), c]``. The down path halves ``H`` ``len(down_dims) - 1`` times and
the up path doubles it back, with skip connections laid out as in Diffusion Policy. An ``H`` that is not a multiple
of ``2 ** (len(down_dims) - 1)`` is zero-padded at the end and the output cropped back, so any ``H >= 1`` works.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import nn
from torch.nn import functional as F


class SinusoidalEmbedding(nn.Module):
    """Sinusoidal embedding of a scalar (Vaswani et al. 2017, Sec. 3.5): for ``i < d/2``,
    ``emb(s)_i = sin(s w_i)``, ``emb(s)_{d/2+i} = cos(s w_i)``, with ``w_i = 10000^(-i / (d/2 - 1))``.

    The flow time ``t`` in [0, 1] is embedded as ``s = scale * t`` (``scale = 1000`` by default, the range of a
    DDPM step index, so that the slow frequencies also see ``t`` change).
    """

    def __init__(self, dim: int, scale: float = 1000.0) -> None:
        super().__init__()
        if dim < 4 or dim % 2:
            raise ValueError(f"embedding dim must be even and >= 4; got {dim}")
        half = dim // 2
        self.scale = scale
        self.register_buffer("freqs", torch.exp(-math.log(10000.0) * torch.arange(half) / (half - 1)), persistent=False)

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        s = (self.scale * t)[:, None] * self.freqs
        return torch.cat([s.sin(), s.cos()], dim=-1)


def time_and_condition(
    x: torch.Tensor, t: torch.Tensor | float, c: torch.Tensor | None, cond_dim: int, n_times: int = 1
) -> tuple[torch.Tensor, torch.Tensor]:
    """A denoiser's time ``[B]`` (``[B, 2]`` when ``n_times = 2``; a scalar or one pair broadcast) and condition
    ``[B, cond_dim]`` (None: an empty one) for the chunks ``x [B, H, A]``; other shapes raise ``ValueError``."""
    b = len(x)
    t = torch.as_tensor(t, dtype=x.dtype, device=x.device)
    shape = (b,) if n_times == 1 else (b, n_times)
    if t.shape not in (shape, shape[1:], ()) or (n_times > 1 and t.ndim == 0):
        raise ValueError(f"time must have shape {list(shape)} (n_times={n_times}); got {tuple(t.shape)}")
    t = t.expand(shape)
    if c is None:
        c = x.new_zeros(b, 0)
    if c.shape != (b, cond_dim):
        raise ValueError(f"condition must have shape [{b}, {cond_dim}]; got {tuple(c.shape)}")
    return t, c


def time_mlp(dim: int, scale: float = 1000.0) -> nn.Sequential:
    """The embedding of a time in [0, 1]: sinusoidal (of ``scale * t``), then ``Linear -> Mish -> Linear``."""
    return nn.Sequential(SinusoidalEmbedding(dim, scale), nn.Linear(dim, 4 * dim), nn.Mish(), nn.Linear(4 * dim, dim))


class Conv1dBlock(nn.Module):
    """``Conv1d`` (same length) -> ``GroupNorm`` -> ``Mish``."""

    def __init__(self, c_in: int, c_out: int, kernel_size: int, n_groups: int) -> None:
        super().__init__()
        self.block = nn.Sequential(
            nn.Conv1d(c_in, c_out, kernel_size, padding=kernel_size // 2), nn.GroupNorm(n_groups, c_out), nn.Mish()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # The Sequential's layers called functionally: the same maths, less per-module overhead at batch size 1.
        conv, norm, _ = self.block
        x = F.conv1d(x, conv.weight, conv.bias, padding=conv.padding)
        return F.mish(F.group_norm(x, norm.num_groups, norm.weight, norm.bias, norm.eps))


class ConditionalResidualBlock1D(nn.Module):
    """Two conv blocks with FiLM in between (Perez et al. 2018): ``h = gamma * conv0(x) + beta``,
    ``out = conv1(h) + W x``, where ``W`` is a 1x1 convolution when the widths differ (identity otherwise).

    As in Diffusion Policy's block, ``(gamma, beta) = Linear(Mish(e))`` are per-channel functions of the embedding
    ``e = [emb(t), c]``; :class:`ConditionalUnet1D` computes them for all its blocks with one stacked ``Linear``
    (the same function, fewer kernel launches) and passes them in as ``film [B, 2 * c_out]``.
    """

    def __init__(self, c_in: int, c_out: int, kernel_size: int, n_groups: int) -> None:
        super().__init__()
        self.c_out = c_out
        self.conv0 = Conv1dBlock(c_in, c_out, kernel_size, n_groups)
        self.conv1 = Conv1dBlock(c_out, c_out, kernel_size, n_groups)
        self.residual = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else None

    def forward(self, x: torch.Tensor, film: torch.Tensor) -> torch.Tensor:
        gamma, beta = film[..., None].chunk(2, dim=1)
        h = torch.addcmul(beta, gamma, self.conv0(x))
        return self.conv1(h) + (x if self.residual is None else self.residual(x))


class ConditionalUnet1D(nn.Module):
    """Velocity network ``v(x, t, c)`` for action chunks.

    Args:
        action_dim: ``A``, the size of one action.
        cond_dim: ``C``, the size of the condition vector.
        down_dims: channel width of each resolution level; ``len(down_dims) - 1`` halvings of ``H``.
        kernel_size: temporal kernel of the conv blocks (odd).
        n_groups: GroupNorm groups; must divide every width.
        time_dim: size of the flow-time embedding (sinusoidal, then ``Linear -> Mish -> Linear``).
        n_times: 1 (a time ``t [B]``) or 2 (an interval ``[B, 2]``; its length gets an embedding of its own).
        time_scale: the embedding's ``scale`` (:class:`SinusoidalEmbedding`); an objective that differentiates the
            network in time (MeanFlow) wants a smooth one (1).
    """

    def __init__(
        self,
        action_dim: int = 2,
        cond_dim: int = 50,
        down_dims: Sequence[int] = (64, 128),
        kernel_size: int = 5,
        n_groups: int = 8,
        time_dim: int = 64,
        n_times: int = 1,
        time_scale: float = 1000.0,
    ) -> None:
        super().__init__()
        down_dims = tuple(int(d) for d in down_dims)
        if n_times not in (1, 2):
            raise ValueError(f"n_times must be 1 (a time) or 2 (an interval); got {n_times!r}")
        if action_dim < 1 or cond_dim < 0:
            raise ValueError(f"need action_dim >= 1 and cond_dim >= 0; got {action_dim}, {cond_dim}")
        if not down_dims or any(d % n_groups for d in down_dims):
            raise ValueError(f"down_dims {down_dims} must be non-empty and divisible by n_groups={n_groups}")
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be odd; got {kernel_size}")
        self.action_dim, self.cond_dim, self.n_times = action_dim, cond_dim, n_times
        self.stride = 2 ** (len(down_dims) - 1)  # H is padded to a multiple of this
        self.time_mlp = time_mlp(time_dim, time_scale)
        if n_times == 2:
            self.interval_mlp = time_mlp(time_dim, time_scale)

        def block(c_in: int, c_out: int) -> ConditionalResidualBlock1D:
            return ConditionalResidualBlock1D(c_in, c_out, kernel_size, n_groups)

        widths = (action_dim, *down_dims)
        self.down = nn.ModuleList()
        for i, (c_in, c_out) in enumerate(zip(widths[:-1], widths[1:])):
            last = i == len(down_dims) - 1
            self.down.append(
                nn.ModuleList(
                    [
                        block(c_in, c_out),
                        block(c_out, c_out),
                        nn.Conv1d(c_out, c_out, 3, 2, 1) if not last else nn.Identity(),
                    ]
                )
            )
        self.mid = nn.ModuleList([block(down_dims[-1], down_dims[-1]), block(down_dims[-1], down_dims[-1])])
        self.up = nn.ModuleList()
        for c_low, c_high in reversed(list(zip(down_dims[:-1], down_dims[1:]))):
            # input: the level below (c_high channels) concatenated with the skip of the same resolution (c_high)
            self.up.append(
                nn.ModuleList(
                    [block(2 * c_high, c_low), block(c_low, c_low), nn.ConvTranspose1d(c_low, c_low, 4, 2, 1)]
                )
            )
        self.final = nn.Sequential(
            Conv1dBlock(down_dims[0], down_dims[0], kernel_size, n_groups), nn.Conv1d(down_dims[0], action_dim, 1)
        )
        # FiLM of every residual block, in forward order: one Linear(Mish(e)) whose output is split per block.
        self.film_sizes = [2 * m.c_out for m in self.modules() if isinstance(m, ConditionalResidualBlock1D)]
        self.film = nn.Sequential(nn.Mish(), nn.Linear(time_dim + cond_dim, sum(self.film_sizes)))

    def forward(self, x: torch.Tensor, t: torch.Tensor | float, c: torch.Tensor | None = None) -> torch.Tensor:
        """Velocity ``[B, H, A]`` at chunk ``x [B, H, A]``, flow time ``t`` (``[B]`` or a scalar; ``[B, 2]`` with
        ``n_times=2``) and condition ``c [B, C]``."""
        if x.ndim != 3 or x.shape[-1] != self.action_dim:
            raise ValueError(f"x must have shape [B, H, {self.action_dim}]; got {tuple(x.shape)}")
        b, h = x.shape[:2]
        t, c = time_and_condition(x, t, c, self.cond_dim, self.n_times)
        emb = self.time_mlp(t) if self.n_times == 1 else self.time_mlp(t[:, 0]) + self.interval_mlp(t[:, 1] - t[:, 0])
        films = iter(self.film(torch.cat([emb, c], dim=-1)).split(self.film_sizes, dim=-1))

        z = x.transpose(1, 2)  # [B, A, H]: time is the conv axis
        pad = -h % self.stride
        if pad:
            z = F.pad(z, (0, pad))
        skips = []
        for res0, res1, down in self.down:
            z = res1(res0(z, next(films)), next(films))
            skips.append(z)
            z = down(z)
        for res in self.mid:
            z = res(z, next(films))
        # As in Diffusion Policy, up step j takes the skip of down level -1-j at its own resolution (the deepest
        # first); the shallowest level's skip is left unused.
        for res0, res1, up in self.up:
            z = torch.cat([z, skips.pop()], dim=1)
            z = up(res1(res0(z, next(films)), next(films)))
        return self.final(z)[..., :h].transpose(1, 2)


def build(
    dims, down_dims: Sequence[int] = (32, 64), kernel_size: int = 5, n_groups: int = 8, time_dim: int = 64
) -> ConditionalUnet1D:
    """The U-Net for a K-CFM's :class:`~kpflow.policies.kcfm.networks.NetworkDims` (any chunk length: ``H`` is halved
    ``len(down_dims) - 1`` times and padded as needed); the options of :class:`ConditionalUnet1D`."""
    return ConditionalUnet1D(dims.action_dim, dims.cond_dim, tuple(down_dims), kernel_size, n_groups, time_dim,
                             n_times=dims.n_times, time_scale=dims.time_scale)  # fmt: skip
