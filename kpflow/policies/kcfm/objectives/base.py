"""The interface every generative objective of an action-chunk policy offers.

An objective says two things about a denoising network ``net(x [B, H, A], t [B], c) -> [B, H, A]`` (``t`` in
[0, 1]): what it is trained to predict for a batch of normalised data chunks ``x1`` (:meth:`Objective.training_target`)
and how a sample is drawn with it from Gaussian noise (:meth:`Objective.sample`). The policy
(:class:`~kpflow.policies.kcfm.KCFM`) owns the data, the condition, the mask and the network; the objective owns the
probability path and its samplers. Families: :mod:`.icfm`, :mod:`.otcfm` (flow matching on :mod:`.paths`' straight path), :mod:`.ddpm`
(diffusion, diffusers' schedulers, as Diffusion Policy trains and samples), :mod:`.meanflow` (average velocities:
one step from noise to data, trained from scratch) and :mod:`.reflow` (a trained flow's own samples as straight
couplings: distillation into few steps).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol

import torch

#: ``net(x, t)`` with the condition already bound: the network as the sampler sees it.
Denoiser = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass
class TrainingTarget:
    """One training example per batch row: regress ``net(x_t, t, c[index])`` onto ``target`` (masked by
    ``mask[index]``). ``index [B]`` says which data row each example came from: the identity except for
    objectives that re-pair noise and data (OT-CFM)."""

    x_t: torch.Tensor  # [B, H, A] the corrupted chunk the network sees
    t: torch.Tensor  # [B] in [0, 1]: the network's time input
    target: torch.Tensor  # [B, H, A] what it must output
    index: torch.Tensor  # [B] int64 rows of the data batch


#: ``net(x, t, c)``: the network being trained, as an objective whose target depends on it sees it.
Network = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


class Objective(Protocol):
    """A generative objective (module docstring).

    ``solvers`` names its samplers, the first the default; ``n_times`` is how many times the network takes per row
    (1: ``t [B]``; 2: ``t [B, 2]``, the start and end of an interval, :mod:`.meanflow`); ``time_scale`` the scale
    of the network's sinusoidal time embedding (:class:`~kpflow.policies.kcfm.networks.unet1d.SinusoidalEmbedding`).
    """

    solvers: tuple[str, ...]
    n_times: int
    time_scale: float

    def training_target(
        self,
        x1: torch.Tensor,
        cond: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        net: Network | None = None,
    ) -> TrainingTarget:
        """Corrupt normalised data chunks ``x1 [B, H, A]`` (conditions ``cond [B, C]``, which a coupling may use)
        with noise drawn from ``generator``; ``net`` is the network being trained, for targets that depend on it."""

    def sample(self, net: Denoiser, noise: torch.Tensor, steps: int, solver: str) -> torch.Tensor:
        """Chunks ``[B, H, A]`` in the data's normalised space, from ``noise ~ N(0, I)`` in ``steps`` network calls
        of ``solver`` (one of :attr:`solvers`)."""


def randn_like(x: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """``N(0, I)`` noise shaped like ``x``, drawn on the generator's device and moved to ``x``'s."""
    device = generator.device if generator is not None else x.device
    return torch.randn(x.shape, generator=generator, device=device, dtype=x.dtype).to(x.device)


def rand(n: int, like: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """``n`` draws of ``U(0, 1)`` on ``like``'s device and dtype."""
    device = generator.device if generator is not None else like.device
    return torch.rand(n, generator=generator, device=device, dtype=like.dtype).to(like.device)


def identity_index(x: torch.Tensor) -> torch.Tensor:
    return torch.arange(len(x), device=x.device)
