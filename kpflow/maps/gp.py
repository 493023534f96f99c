"""Gaussian-process transportation map (the paper's GP transport; gpytorch exact GP).

phi(x) = A x + t + f(x),  f ~ GP(0, k) fitted on the residuals target_i - (A source_i + t),

so far from every keypoint f -> 0 and phi falls back to the affine (by default rigid) motion: the
zero-transport prior.

Default hyper-parameters come from the keypoints' own geometry, not from the marginal likelihood: a Matern 3/2 kernel
whose length-scale is ``LENGTHSCALE`` = 0.8 times the source keypoints' diameter (their largest pairwise distance: the
distance between the farthest groups, which one far keypoint, a gripper beside an object, does not shrink as it
shrinks an RMS spread), an output variance equal to the residuals' mean square and a noise variance ``NOISE`` = 1e-6
of it, so the map interpolates its keypoints (``iters=0``: nothing is optimised, and a fit is one Cholesky
factorisation). The marginal likelihood of ten keypoints says little about how the space between two groups of them
should bend: free maximum likelihood picked length-scales that left a path between a start and a goal frame turned
independently with the compromise rotation, where this prior did not (``benchmarks/map_suite.py --split tuning
--candidates``, results/maps_suite.md). ``iters > 0`` fits them
by maximum likelihood from these values (``lengthscale_bounds`` and ``restarts`` then apply). ``predict`` gives the posterior mean and latent variance of f (the uncertainty of phi),
``jacobian`` the Jacobian of the mean, ``jacobian_variance`` the variance of each Jacobian entry, and ``sample``
joint posterior draws (one smooth map per sample). The inverse is solved by Newton iterations from the affine
inverse; it exists where J stays non-singular, which the GP does not guarantee (``exact_inverse = False``).
"""

from __future__ import annotations

import gpytorch
import torch

from kpflow.maps.affine import AlignedMap
from kpflow.maps.base import jacobian_autograd, newton_inverse
from kpflow.maps.gp_regression import GPRegressor

#: the default length-scale, in units of the source keypoints' diameter (module docstring)
LENGTHSCALE = 0.8
#: the default noise variance, as a fraction of the residuals' mean square
NOISE = 1e-6


class GPMap(AlignedMap):
    """Affine alignment plus a gpytorch GP on the residual (module docstring).

    Args:
        alignment: ``"rigid"``, ``"similarity"``, ``"affine"``, ``"translation"`` or ``"none"``.
        kernel, mean, likelihood: gpytorch modules (templates, copied at each fit; default a scaled Matern 3/2
            kernel, a zero mean and a Gaussian likelihood), e.g. ``kernel=gpytorch.kernels.RBFKernel()``.
        lengthscale: the kernel's length-scale in units of ``lengthscale_unit`` (module docstring).
        lengthscale_unit: ``"diameter"`` (the source keypoints' largest pairwise distance) or ``"spread"`` (their RMS
            distance from their centroid).
        noise: the noise variance as a fraction of the residuals' mean square.
        iters: L-BFGS iterations of maximum likelihood from those values (0: the geometric prior as it is).
        lengthscale_bounds: ``(low, high)`` of the length-scale in keypoint units (e.g. ``(10, 50)`` where a
            frame's keypoints are 5 apart), for ``iters > 0``.
        restarts: further hyper-parameter optimisations from other length-scales; the best likelihood is kept.
        min_noise, fixed_noise, max_sample_bytes: see :class:`~kpflow.maps.gp_regression.GPRegressor` (checked at
            construction: a value out of range raises ``ValueError`` naming it).
    """

    exact_inverse = False

    def __init__(
        self,
        alignment: str = "rigid",
        lengthscale: float | None = LENGTHSCALE,
        noise: float = NOISE,
        min_noise: float | None = None,
        fixed_noise: bool = False,
        iters: int = 0,
        max_sample_bytes: int | None = None,
        kernel: gpytorch.kernels.Kernel | None = None,
        mean: gpytorch.means.Mean | None = None,
        likelihood: gpytorch.likelihoods.GaussianLikelihood | None = None,
        lengthscale_bounds: tuple[float, float] | None = None,
        restarts: int = 0,
        lengthscale_unit: str = "diameter",
    ) -> None:
        super().__init__(alignment)
        kernel = kernel if kernel is not None else gpytorch.kernels.MaternKernel(nu=1.5)
        self.gp = GPRegressor(
            lengthscale=lengthscale, noise=noise, min_noise=min_noise, fixed_noise=fixed_noise, iters=iters,
            max_sample_bytes=max_sample_bytes, kernel=kernel, mean=mean, likelihood=likelihood,
            lengthscale_bounds=lengthscale_bounds, restarts=restarts, lengthscale_unit=lengthscale_unit,
        )  # fmt: skip

    def _fit(self, source: torch.Tensor, target: torch.Tensor) -> None:
        self._fit_alignment(source, target)
        base = self.alignment._forward(source)
        self.gp.fit(source[0], (target - base)[0])

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.alignment._forward(x) + self.gp.mean(x[0])[None]

    def _predict(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, var = self.gp.predict(x[0])
        return self.alignment._forward(x) + mean[None], var[None]

    def _jacobian(self, x: torch.Tensor) -> torch.Tensor:
        return self.alignment._jacobian(x) + jacobian_autograd(lambda z: self.gp.mean(z[0])[None], x)

    def _sample(self, x: torch.Tensor, n: int, generator: torch.Generator | None) -> torch.Tensor:
        return self.alignment._forward(x)[None] + self.gp.sample(x[0], n, generator)[:, None]

    def _inverse(self, y: torch.Tensor) -> torch.Tensor:
        return newton_inverse(self._forward, self._jacobian, y, self.alignment._inverse(y))

    def jacobian_variance(self, x) -> torch.Tensor:
        """Posterior variance of each entry of J(x): ``[..., D, D]`` (row i, column j: var d phi_i / d x_j)."""
        flat, shape = self._flatten(x)
        gv = self.gp.gradient_variance(flat[0])  # [M, D]
        return gv[:, None, :].expand(-1, self.dim, -1).reshape(*shape, self.dim)
