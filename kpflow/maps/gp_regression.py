"""Multi-output exact GP regression with gpytorch: one kernel, mean and likelihood shared by all D outputs.

Inputs are standardised by the training inputs' mean and RMS spread; outputs are divided by their RMS (so the
prior mean is zero in original units). The kernel, mean and likelihood are injected as gpytorch modules (a kernel
that is not a ``ScaleKernel`` is wrapped in one); each fit works on its own deep copy, so one configured template
serves every fit. Hyper-parameters maximise the exact marginal likelihood (Rasmussen & Williams 2006, Eq. 5.8) with
L-BFGS, from the initial length-scale and from ``restarts`` more, spread log-uniformly; the best likelihood wins.
Length-scale bounds are given in the keypoints' own units. Posterior (Eqs. 2.25-2.26):

    mean(x) = k(x, X) (K + s_n^2 I)^-1 Y,      var(x) = k(x, x) - k(x, X) (K + s_n^2 I)^-1 k(X, x).

Derivative of the GP (Eq. 9.1 and Solak et al. 2003): d mean / dx by autograd through the posterior mean, and
var(d f / dx_j) = var_0(d f / dx_j) - g_j^T (K + s_n^2 I)^-1 g_j with g_j = d k(X, x) / d x_j (by autograd) and the
prior var_0 = -d^2 k / d tau_j^2 at tau = 0 of the stationary kernel: s^2 / l^2 (RBF), 3 s^2 / l^2 (Matern 3/2),
5 s^2 / (3 l^2) (Matern 5/2), summed over the parts of a sum; Matern 1/2 is not mean-square differentiable.
"""

from __future__ import annotations

import copy
import math

import gpytorch
import torch
from linear_operator.utils.cholesky import psd_safe_cholesky
from torch import nn

from kpflow.maps.validation import check_count, check_positive, scale_floor

#: default limit on the memory of the joint posterior covariance ``sample`` builds (D x M x M entries for M query
#: points and D outputs; quadratic in M): 1 GiB
MAX_SAMPLE_BYTES = 1 << 30


def _format_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    raise AssertionError  # unreachable


class _ExactGP(gpytorch.models.ExactGP):
    """D independent outputs as a batch sharing one kernel and mean: inputs ``[D, N, d]``, targets ``[D, N]``."""

    def __init__(
        self, x: torch.Tensor, y: torch.Tensor, likelihood, mean: gpytorch.means.Mean, kernel: gpytorch.kernels.Kernel
    ):
        super().__init__(x, y, likelihood)
        self.mean_module, self.covar_module = mean, kernel

    def forward(self, x: torch.Tensor) -> gpytorch.distributions.MultivariateNormal:
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


def _lengthscale_kernels(kernel: gpytorch.kernels.Kernel) -> list[gpytorch.kernels.Kernel]:
    return [k for k in kernel.modules() if isinstance(k, gpytorch.kernels.Kernel) and k.has_lengthscale]


def derivative_prior(kernel: gpytorch.kernels.Kernel) -> torch.Tensor:
    """var_0(d f / d x_j) ``[d]`` (or a scalar) of a stationary kernel (module docstring), in its own units."""
    k = gpytorch.kernels
    if isinstance(kernel, k.ScaleKernel):
        return kernel.outputscale * derivative_prior(kernel.base_kernel)
    if isinstance(kernel, k.AdditiveKernel):
        return sum(derivative_prior(part) for part in kernel.kernels)
    if isinstance(kernel, k.RBFKernel):
        return 1.0 / kernel.lengthscale.squeeze() ** 2
    if isinstance(kernel, k.MaternKernel):
        if kernel.nu == 0.5:
            raise ValueError(
                "a Matern 1/2 kernel is not mean-square differentiable: the Jacobian's variance is infinite"
            )
        return (3.0 if kernel.nu == 1.5 else 5.0 / 3.0) / kernel.lengthscale.squeeze() ** 2
    raise ValueError(
        f"the Jacobian's variance is derived for RBF and Matern kernels and their scaled sums, not {type(kernel).__name__}"
    )


class GPRegressor(nn.Module):
    """Exact GP regression ``x [N, d] -> y [N, D]`` (module docstring).

    Args:
        kernel: a gpytorch kernel (template; default ``ScaleKernel(RBFKernel())``), e.g. ``MaternKernel(nu=2.5)``,
            ``RBFKernel() + MaternKernel(nu=1.5)`` or a product; wrapped in a ``ScaleKernel`` unless it is one.
        mean: a gpytorch mean (template; default ``ZeroMean()``: far from the data f -> 0).
        likelihood: a gpytorch Gaussian likelihood (template; default one with the noise bounded by ``min_noise``).
        lengthscale: initial length-scale in units of ``lengthscale_unit`` (``None``: 1.0 standardised unit, or the
            bounds' geometric mean).
        lengthscale_unit: ``"spread"``: the training inputs' RMS spread about their mean (the standardised unit);
            ``"diameter"``: their largest pairwise distance.
        lengthscale_bounds: ``(low, high)`` of every length-scale, in the units of the inputs (the keypoints'),
            or None (positive, unbounded).
        outputscale: initial output variance (standardised units).
        noise: initial noise variance in standardised output units; ``fixed_noise=True`` keeps it.
        min_noise: lower bound of the default likelihood's noise variance (standardised units); default 1e-6 in
            float64, 1e-4 in float32 (where a smaller floor leaves the kernel matrix numerically singular).
        iters: L-BFGS iterations for the hyper-parameters (0 keeps the initial values).
        restarts: further optimisations from length-scales spread log-uniformly over a decade either side of the
            initial one (within the bounds), deterministic; the best marginal likelihood is kept.
        max_sample_bytes: refuse ``sample`` when its joint covariance would need more memory than this
            (``None``: :data:`MAX_SAMPLE_BYTES`, 1 GiB).

    After ``fit`` the hyper-parameters are frozen (``requires_grad=False``), as the neural maps' weights are, so
    outputs carry an autograd graph only when the query itself requires grad.
    """

    def __init__(
        self,
        lengthscale: float | None = None,
        outputscale: float = 1.0,
        noise: float = 1e-4,
        min_noise: float | None = None,
        fixed_noise: bool = False,
        iters: int = 10,
        max_sample_bytes: int | None = None,
        kernel: gpytorch.kernels.Kernel | None = None,
        mean: gpytorch.means.Mean | None = None,
        likelihood: gpytorch.likelihoods.GaussianLikelihood | None = None,
        lengthscale_bounds: tuple[float, float] | None = None,
        restarts: int = 0,
        lengthscale_unit: str = "spread",
    ) -> None:
        super().__init__()
        check_positive("lengthscale", lengthscale, optional=True, what=" (the initial length-scale; None: 1.0)")
        if lengthscale_unit not in ("spread", "diameter"):
            raise ValueError(f"lengthscale_unit must be 'spread' or 'diameter', got {lengthscale_unit!r}")
        self.lengthscale_unit = lengthscale_unit
        check_positive("outputscale", outputscale, what=" (the initial output variance)")
        check_positive("noise", noise, what=" (the initial noise variance)")
        check_positive("min_noise", min_noise, optional=True, what=" (the noise variance's lower bound; None: default)")
        check_count("iters", iters, 0, what=" (L-BFGS iterations)")
        check_count("restarts", restarts, 0, what=" (further optimisations from other length-scales)")
        check_positive("max_sample_bytes", max_sample_bytes, optional=True, what=" (the memory limit of sample())")
        for name, value, kind in (("kernel", kernel, gpytorch.kernels.Kernel), ("mean", mean, gpytorch.means.Mean),
                                  ("likelihood", likelihood, gpytorch.likelihoods.GaussianLikelihood)):  # fmt: skip
            if value is not None and not isinstance(value, kind):
                raise ValueError(f"{name} must be a {kind.__module__}.{kind.__name__}, got {type(value).__name__}")
        if lengthscale_bounds is not None:
            low, high = (float(v) for v in lengthscale_bounds)
            if not (0 < low < high < float("inf")):
                raise ValueError(
                    f"lengthscale_bounds must be (low, high) with 0 < low < high < inf, got {tuple(lengthscale_bounds)}"
                )
            lengthscale_bounds = (low, high)
        kernel = kernel if kernel is not None else gpytorch.kernels.RBFKernel()
        kernel = kernel if isinstance(kernel, gpytorch.kernels.ScaleKernel) else gpytorch.kernels.ScaleKernel(kernel)
        if not _lengthscale_kernels(kernel):
            raise ValueError(f"the kernel {type(kernel).__name__} has no length-scale to fit")
        # the templates, kept in a tuple so that they are not sub-modules (their parameters are never fitted)
        self.templates = (kernel, mean if mean is not None else gpytorch.means.ZeroMean(), likelihood)
        self.lengthscale_bounds, self.restarts = lengthscale_bounds, restarts
        self.max_sample_bytes = max_sample_bytes
        self.init_lengthscale, self.init_outputscale = lengthscale, outputscale
        self.init_noise, self.min_noise, self.fixed_noise, self.iters = noise, min_noise, fixed_noise, iters
        self.model: _ExactGP | None = None

    def fit(self, x: torch.Tensor, y: torch.Tensor) -> "GPRegressor":
        n, d_out = y.shape
        self.x_mean = x.mean(0)
        self.x_scale = (x - self.x_mean).square().sum(-1).mean().sqrt().clamp_min(scale_floor(x))
        self.y_scale = y.square().mean().sqrt().clamp_min(1e-12 * self.x_scale)
        xs = ((x - self.x_mean) / self.x_scale).expand(d_out, n, x.shape[-1])
        ys = (y / self.y_scale).T.contiguous()
        bounds = (
            None if self.lengthscale_bounds is None else tuple(b / float(self.x_scale) for b in self.lengthscale_bounds)
        )
        unit = 1.0
        if self.lengthscale_unit == "diameter" and self.init_lengthscale:
            unit = float(torch.pdist(x.detach()).max() / self.x_scale) if n > 1 else 1.0
        start = (
            self.init_lengthscale * unit
            if self.init_lengthscale
            else (math.sqrt(bounds[0] * bounds[1]) if bounds else 1.0)
        )
        offsets = sorted(
            (u for u in torch.linspace(-1, 1, self.restarts + 2).tolist() if abs(u) > 1e-9), key=lambda u: (-abs(u), u)
        )
        starts = [start] + [
            start * 10.0**u for u in offsets[: self.restarts]
        ]  # a decade down and up first, then between
        if bounds:
            starts = [min(max(s, bounds[0] * 1.001), bounds[1] * 0.999) for s in starts]
        best = None
        for lengthscale in starts:
            model, likelihood = self._model(xs, ys, lengthscale, bounds)
            loss = self._optimise(model, likelihood, xs, ys) if self.iters > 0 else 0.0
            if best is None or loss < best[0]:
                best = (loss, model, likelihood)
        _, model, likelihood = best
        for p in model.parameters():  # the likelihood's too (a sub-module of the model)
            p.requires_grad_(False)
        model.eval()
        likelihood.eval()
        self.model, self.likelihood = model, likelihood
        self._chol = None  # built on first use by gradient_variance
        return self

    def _model(
        self, xs: torch.Tensor, ys: torch.Tensor, lengthscale: float, bounds: tuple | None
    ) -> tuple[_ExactGP, object]:
        """A fresh model from the templates at the initial hyper-parameters."""
        kernel, mean, likelihood = (copy.deepcopy(t) for t in self.templates)
        if likelihood is None:
            min_noise = self.min_noise or (1e-6 if xs.dtype == torch.float64 else 1e-4)
            likelihood = gpytorch.likelihoods.GaussianLikelihood(
                noise_constraint=gpytorch.constraints.GreaterThan(min_noise)
            ).to(xs)
            likelihood.noise = max(self.init_noise, min_noise * 1.01)
        else:
            likelihood = likelihood.to(xs)
        if bounds is not None:
            for k in _lengthscale_kernels(kernel):
                k.register_constraint("raw_lengthscale", gpytorch.constraints.Interval(*bounds))
        model = _ExactGP(xs, ys, likelihood, mean, kernel).to(xs)
        for k in _lengthscale_kernels(model.covar_module):  # values set in the data's dtype, after the move
            k.lengthscale = lengthscale
        model.covar_module.outputscale = self.init_outputscale
        if self.fixed_noise:
            likelihood.raw_noise.requires_grad_(False)
        return model, likelihood

    def _train_cholesky(self) -> torch.Tensor:
        if self._chol is None:
            train = self.model.train_inputs[0][0]
            with torch.no_grad():
                k = self.model.covar_module(train).to_dense()
                k = k + self.likelihood.noise * torch.eye(train.shape[0], dtype=k.dtype, device=k.device)
                self._chol = psd_safe_cholesky(k)
        return self._chol

    def _optimise(self, model, likelihood, xs, ys) -> float:
        """L-BFGS on the negative marginal log likelihood; its final value."""
        model.train()
        likelihood.train()
        params = [p for p in model.parameters() if p.requires_grad]
        opt = torch.optim.LBFGS(
            params,
            lr=1.0,
            max_iter=self.iters,
            tolerance_grad=1e-4,
            tolerance_change=1e-6,
            line_search_fn="strong_wolfe",
        )
        mll = gpytorch.mlls.ExactMarginalLogLikelihood(likelihood, model)

        def closure():
            opt.zero_grad()
            loss = -mll(model(xs), ys).sum()
            loss.backward()
            return loss

        with gpytorch.settings.cholesky_jitter(1e-8 if xs.dtype == torch.float64 else 1e-6):
            opt.step(closure)
            with torch.no_grad():
                return float(-mll(model(xs), ys).sum())

    # ------------------------------------------------------------------ hyper-parameters (original units)
    @property
    def lengthscale(self) -> torch.Tensor:
        """The fitted length-scale in input units (of the kernel's one length-scale kernel)."""
        kernels = _lengthscale_kernels(self.model.covar_module)
        if len(kernels) != 1:
            raise ValueError(f"the kernel has {len(kernels)} length-scales; read them from gp.model.covar_module")
        return kernels[0].lengthscale.detach().squeeze() * self.x_scale

    @property
    def outputscale(self) -> torch.Tensor:
        return self.model.covar_module.outputscale.detach() * self.y_scale**2

    @property
    def noise(self) -> torch.Tensor:
        return self.likelihood.noise.detach().squeeze() * self.y_scale**2

    # ------------------------------------------------------------------ posterior
    def _standardise(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self.x_mean) / self.x_scale).expand(self.model.train_targets.shape[0], *x.shape)

    def posterior(self, x: torch.Tensor) -> gpytorch.distributions.MultivariateNormal:
        """Latent posterior at ``x [M, d]`` in standardised units (batch over the D outputs); differentiable in
        ``x`` (the hyper-parameters are frozen, so a query that does not require grad builds no graph)."""
        with gpytorch.settings.debug(False), gpytorch.settings.skip_posterior_variances(False):
            return self.model(self._standardise(x))

    def mean(self, x: torch.Tensor) -> torch.Tensor:
        with gpytorch.settings.debug(False), gpytorch.settings.skip_posterior_variances(True):
            return self.model(self._standardise(x)).mean.T * self.y_scale

    def predict(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Posterior mean ``[M, D]`` and latent variance ``[M, D]`` (noise excluded)."""
        post = self.posterior(x)
        return post.mean.T * self.y_scale, post.variance.T.clamp_min(0.0) * self.y_scale**2

    def sample(self, x: torch.Tensor, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Joint posterior samples ``[n, M, D]`` (one smooth function per sample and output).

        Joint samples need the full M x M posterior covariance per output (and its Cholesky factor): memory
        quadratic in M. Raises ``ValueError`` before allocating when it would exceed ``max_sample_bytes``.
        """
        self._check_sample_memory(x)
        post = self.posterior(x)
        cov = post.covariance_matrix  # [D, M, M]
        m = x.shape[0]
        jitter = 1e-10 if x.dtype == torch.float64 else 1e-6
        chol = torch.linalg.cholesky(cov + jitter * torch.eye(m, dtype=x.dtype, device=x.device))
        eps = torch.randn(n, cov.shape[0], m, 1, generator=generator, dtype=x.dtype, device=x.device)
        f = post.mean[..., None] + chol @ eps  # [n, D, M, 1]
        return f.squeeze(-1).transpose(1, 2) * self.y_scale

    def _check_sample_memory(self, x: torch.Tensor) -> None:
        m, d_out = x.shape[0], self.model.train_targets.shape[0]
        need = d_out * m * m * x.element_size()
        limit = MAX_SAMPLE_BYTES if self.max_sample_bytes is None else self.max_sample_bytes
        if need > limit:
            raise ValueError(
                f"sample() at {m} points needs a joint posterior covariance of {d_out} x {m} x {m} {x.dtype} "
                f"({_format_bytes(need)}, plus as much again for its Cholesky factor), over the limit of "
                f"{_format_bytes(limit)} (max_sample_bytes): the cost is quadratic in the number of points. "
                "Sample fewer points, or in chunks (each chunk is then a separate joint draw), or use predict() "
                "for the marginal mean and variance at every point"
            )

    def gradient_variance(self, x: torch.Tensor) -> torch.Tensor:
        """var(d f_i / d x_j) ``[M, d]`` (the same for every output i since the kernel is shared; module docstring)."""
        xs = self._standardise(x)[0].detach().requires_grad_(True)  # [M, d]
        train = self.model.train_inputs[0][0]  # [N, d]
        kern = self.model.covar_module
        with torch.enable_grad():
            kx = kern(xs, train).to_dense()  # [M, N]
            g = torch.stack(
                [torch.autograd.grad(kx[:, i].sum(), xs, retain_graph=True)[0] for i in range(train.shape[0])], 1
            )
        with torch.no_grad():
            n = train.shape[0]
            flat = g.transpose(0, 1).reshape(n, -1)  # [N, M*d]
            quad = (flat * torch.cholesky_solve(flat, self._train_cholesky())).sum(0).reshape(x.shape[0], -1)
            prior = derivative_prior(kern)
        return (prior - quad).clamp_min(0.0) * (self.y_scale / self.x_scale) ** 2
