"""DDPM training with DDIM sampling, as Diffusion Policy trains and samples (Chi et al. 2023; Ho et al. 2020,
"Denoising Diffusion Probabilistic Models", eq. 4 and Alg. 1; Song et al. 2021, "Denoising Diffusion Implicit
Models", eq. 12 with ``eta = 0``), through diffusers' schedulers.

Training (``T`` diffusion steps, the squared-cosine schedule ``alpha_bar`` of Nichol & Dhariwal 2021 that DP uses):
with ``k ~ U{0, .., T-1}`` and ``eps ~ N(0, I)``,

    x_k = sqrt(alpha_bar_k) x1 + sqrt(1 - alpha_bar_k) eps,       L = E || eps_theta(x_k, k / T, c) - eps ||^2.

Sampling runs ``steps`` deterministic DDIM updates from pure noise over the ``trailing`` spacing of the ``T`` steps
(the first update starts from ``k = T - 1``, so one step already goes from noise to data):

    x0_hat = (x_k - sqrt(1 - alpha_bar_k) eps_theta) / sqrt(alpha_bar_k)   (clipped to [-1, 1], as DP does),
    x_{k'} = sqrt(alpha_bar_{k'}) x0_hat + sqrt(1 - alpha_bar_{k'}) eps_theta.

The network sees the step as ``t = k / T`` in [0, 1), the same time input the flows use.
"""

from __future__ import annotations

import torch
from diffusers import DDIMScheduler, DDPMScheduler

from .base import Denoiser, TrainingTarget, identity_index, randn_like


class DDPM:
    """Denoising diffusion (module docstring).

    Its one sampler is DDIM (``solvers = ("ddim",)``).

    Args:
        train_steps: the number of diffusion steps ``T`` (DP: 100).
        clip_sample: clip each DDIM estimate of the clean chunk to [-1, 1] (the chunks' normalised range).
    """

    solvers = ("ddim",)
    n_times = 1
    time_scale = 1000.0

    def __init__(self, train_steps: int = 100, clip_sample: bool = True) -> None:
        if isinstance(train_steps, bool) or not isinstance(train_steps, int) or train_steps < 2:
            raise ValueError(f"train_steps must be an integer >= 2; got {train_steps!r}")
        self.train_steps = train_steps
        common = dict(
            num_train_timesteps=train_steps,
            beta_schedule="squaredcos_cap_v2",
            clip_sample=clip_sample,
            prediction_type="epsilon",
        )
        self.noise_scheduler = DDPMScheduler(**common)
        self.sampler = DDIMScheduler(**common, set_alpha_to_one=True, timestep_spacing="trailing")

    @property
    def alphas_cumprod(self) -> torch.Tensor:
        """``alpha_bar_k`` for ``k = 0..T-1`` (float32)."""
        return self.noise_scheduler.alphas_cumprod

    def training_target(
        self, x1: torch.Tensor, cond: torch.Tensor | None = None, generator: torch.Generator | None = None, net=None
    ) -> TrainingTarget:
        eps = randn_like(x1, generator)
        device = generator.device if generator is not None else x1.device
        k = torch.randint(0, self.train_steps, (len(x1),), generator=generator, device=device).to(x1.device)
        x_k = self.noise_scheduler.add_noise(x1, eps, k)
        return TrainingTarget(x_k, k.to(x1.dtype) / self.train_steps, eps, identity_index(x1))

    def sample(self, net: Denoiser, noise: torch.Tensor, steps: int, solver: str = "ddim") -> torch.Tensor:
        if solver != "ddim":
            raise ValueError(f"a diffusion samples with DDIM only (solver='ddim'); got {solver!r}")
        if not 1 <= steps <= self.train_steps:
            raise ValueError(f"DDIM steps must be in 1..{self.train_steps} (the diffusion steps); got {steps}")
        self.sampler.set_timesteps(steps, device=noise.device)
        x = noise
        for k in self.sampler.timesteps:
            t = torch.full((len(x),), float(k) / self.train_steps, device=x.device, dtype=x.dtype)
            x = self.sampler.step(net(x, t), int(k), x).prev_sample
        return x
