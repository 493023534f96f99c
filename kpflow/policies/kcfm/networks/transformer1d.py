"""A small transformer denoiser for action chunks, the alternative to :class:`~.unet1d.ConditionalUnet1D` with the
same call ``net(x [B, H, A], t [B], c [B, C]) -> [B, H, A]``.

Tokens: one per chunk step, ``Linear(A -> d)(x_h) + p_h`` with a learned position ``p_h``, preceded by one condition
token ``MLP([emb(t), c])`` (the sinusoidal time embedding of :class:`~.unet1d.SinusoidalEmbedding`; with
``n_times=2``, an interval ``(s, t)``: ``MLP([emb(s), emb(t - s), c])``). A pre-norm
``torch.nn.TransformerEncoder`` (``n_layers`` layers of ``n_heads``-head self-attention and a GELU MLP of width
``4 d``) mixes them; the chunk tokens are read out by ``Linear(d -> A)``. Smaller than Diffusion Policy's
encoder-decoder transformer (Chi et al. 2023, Sec. 3.3), which feeds the condition through cross-attention; here
every step attends to the condition token directly.
"""

from __future__ import annotations

import torch
from torch import nn

from .unet1d import SinusoidalEmbedding, time_and_condition


class ConditionalTransformer1D(nn.Module):
    """Transformer denoiser (module docstring).

    Args:
        action_dim, cond_dim: ``A`` and ``C``.
        horizon: the longest chunk ``H`` it takes (the number of learned positions).
        d_model, n_layers, n_heads: the encoder's width, depth and heads (``n_heads`` must divide ``d_model``).
        time_dim: size of the time embedding.
        dropout: attention and MLP dropout while training.
        n_times: 1 (a time ``t [B]``) or 2 (an interval ``[B, 2]``).
        time_scale: the time embedding's ``scale`` (:class:`~.unet1d.SinusoidalEmbedding`).
    """

    def __init__(
        self,
        action_dim: int = 2,
        cond_dim: int = 50,
        horizon: int = 16,
        d_model: int = 128,
        n_layers: int = 4,
        n_heads: int = 4,
        time_dim: int = 64,
        dropout: float = 0.0,
        n_times: int = 1,
        time_scale: float = 1000.0,
    ) -> None:
        super().__init__()
        if n_times not in (1, 2):
            raise ValueError(f"n_times must be 1 (a time) or 2 (an interval); got {n_times!r}")
        if action_dim < 1 or cond_dim < 0 or horizon < 1 or n_layers < 1:
            raise ValueError(
                f"need action_dim, horizon, n_layers >= 1 and cond_dim >= 0; got {action_dim}, {horizon}, {n_layers}, {cond_dim}"
            )
        if n_heads < 1 or d_model % n_heads:
            raise ValueError(f"n_heads={n_heads} must divide d_model={d_model}")
        self.action_dim, self.cond_dim, self.horizon, self.n_times = action_dim, cond_dim, horizon, n_times
        self.time_emb = SinusoidalEmbedding(time_dim, time_scale)
        self.cond_token = nn.Sequential(
            nn.Linear(n_times * time_dim + cond_dim, 4 * d_model), nn.Mish(), nn.Linear(4 * d_model, d_model)
        )
        self.embed = nn.Linear(action_dim, d_model)
        self.position = nn.Parameter(torch.zeros(1, horizon + 1, d_model))
        nn.init.normal_(self.position, std=0.02)
        layer = nn.TransformerEncoderLayer(
            d_model, n_heads, 4 * d_model, dropout, activation="gelu", batch_first=True, norm_first=True
        )
        self.encoder = nn.TransformerEncoder(layer, n_layers, norm=nn.LayerNorm(d_model), enable_nested_tensor=False)
        self.head = nn.Linear(d_model, action_dim)

    def forward(self, x: torch.Tensor, t: torch.Tensor | float, c: torch.Tensor | None = None) -> torch.Tensor:
        """Output ``[B, H, A]`` at chunk ``x [B, H, A]``, time ``t`` (``[B]`` or a scalar; ``[B, 2]`` with ``n_times=2``)
        and condition ``c [B, C]``."""
        if x.ndim != 3 or x.shape[-1] != self.action_dim or not 1 <= x.shape[1] <= self.horizon:
            raise ValueError(f"x must have shape [B, H <= {self.horizon}, {self.action_dim}]; got {tuple(x.shape)}")
        h = x.shape[1]
        t, c = time_and_condition(x, t, c, self.cond_dim, self.n_times)
        times = [self.time_emb(t)] if self.n_times == 1 else [self.time_emb(t[:, 0]), self.time_emb(t[:, 1] - t[:, 0])]
        cond = self.cond_token(torch.cat([*times, c], dim=-1))[:, None]
        tokens = torch.cat([cond, self.embed(x)], dim=1) + self.position[:, : h + 1]
        return self.head(self.encoder(tokens)[:, 1:])


def build(
    dims, d_model: int = 128, n_layers: int = 4, n_heads: int = 4, time_dim: int = 64, dropout: float = 0.0
) -> ConditionalTransformer1D:
    """The transformer for a K-CFM's :class:`~kpflow.policies.kcfm.networks.NetworkDims` (one learned position per
    step of its chunk); the options of :class:`ConditionalTransformer1D`."""
    return ConditionalTransformer1D(dims.action_dim, dims.cond_dim, dims.horizon, d_model, n_layers, n_heads, time_dim,
                                    dropout, n_times=dims.n_times, time_scale=dims.time_scale)  # fmt: skip
