"""The one interface every transportation map implements.

A map phi: R^D -> R^D is fitted on keypoint pairs so that phi(source_i) ~= target_i. Families implement
four private methods on flat tensors ``[B, M, D]`` (B = number of fitted keypoint sets, 1 when unbatched);
this class handles validation and reshaping, so every public method accepts any leading dimensions.

Batching: ``fit(source [*S, N, D], target [*S, N, D])`` fits one map per keypoint set (families that support
it; see ``supports_batch``). A query ``x [*S, ..., D]`` is then transported by the matching map; a query whose
leading dimensions are not ``S`` is transported by every map, giving ``[*S, *x.shape[:-1], D]``.
"""

from __future__ import annotations

import abc
from typing import Self

import torch
from torch import nn

from kpflow.maps.validation import as_float_tensor, check_finite, check_pairs


class TransportMap(nn.Module, abc.ABC):
    """Base class of all transportation maps (see module docstring for shapes)."""

    #: minimum number of keypoint pairs the family can be fitted on
    min_points: int = 1
    #: whether ``fit`` accepts a batch of keypoint sets
    supports_batch: bool = False
    #: whether ``inverse`` is exact (analytic or solved to tolerance) rather than approximate
    exact_inverse: bool = True

    def __init__(self) -> None:
        super().__init__()
        self.batch_shape: torch.Size | None = None
        self.dim: int | None = None
        self.register_buffer("_source", None, persistent=True)
        self.register_buffer("_target", None, persistent=True)

    # ------------------------------------------------------------------ public API
    def fit(self, source, target) -> Self:
        """Fit phi with phi(source) ~= target; returns ``self``."""
        source, target = check_pairs(source, target, self.required_points)
        batch = source.shape[:-2]
        if len(batch) and not self.supports_batch:
            raise ValueError(
                f"{type(self).__name__} fits one keypoint set at a time; got a batch of shape "
                f"{tuple(batch)} (AffineMap and ILWRMap fit batches)"
            )
        self.batch_shape, self.dim = batch, source.shape[-1]
        self._source, self._target = source, target
        n, d = source.shape[-2:]
        self._fit(source.reshape(-1, n, d), target.reshape(-1, n, d))
        return self

    def forward(self, x) -> torch.Tensor:
        """phi(x) for ``x [..., D]``."""
        flat, out_shape = self._flatten(x)
        return self._forward(flat).reshape(out_shape)

    def inverse(self, y) -> torch.Tensor:
        """phi^-1(y) for ``y [..., D]``."""
        flat, out_shape = self._flatten(y, name="y")
        return self._inverse(flat).reshape(out_shape)

    def jacobian(self, x) -> torch.Tensor:
        """J(x) = d phi / d x, shape ``[..., D, D]`` (row i: derivatives of output i)."""
        flat, out_shape = self._flatten(x)
        return self._jacobian(flat).reshape(*out_shape, self.dim)

    def predict(self, x) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean phi(x) and per-coordinate epistemic variance, both ``[..., D]`` (zero variance by default)."""
        flat, out_shape = self._flatten(x)
        mean, var = self._predict(flat)
        return mean.reshape(out_shape), var.reshape(out_shape)

    def sample(self, x, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` plausible maps evaluated at ``x``: ``[n, ..., D]``. One sample is one smooth function, so a
        trajectory keeps its shape within a sample."""
        flat, out_shape = self._flatten(x)
        return self._sample(flat, n, generator).reshape(n, *out_shape)

    def required_points(self, dim: int) -> int:
        """Fewest keypoint pairs a fit in ``dim`` dimensions needs."""
        return self.min_points

    @property
    def fitted(self) -> bool:
        return self.dim is not None

    # ------------------------------------------------------------------ to implement
    @abc.abstractmethod
    def _fit(self, source: torch.Tensor, target: torch.Tensor) -> None: ...

    @abc.abstractmethod
    def _forward(self, x: torch.Tensor) -> torch.Tensor: ...

    def _inverse(self, y: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError(f"{type(self).__name__} has no inverse")

    def _jacobian(self, x: torch.Tensor) -> torch.Tensor:
        return jacobian_autograd(self._forward, x)

    def _predict(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean = self._forward(x)
        return mean, torch.zeros_like(mean)

    def _sample(self, x: torch.Tensor, n: int, generator: torch.Generator | None) -> torch.Tensor:
        """Default: one shared standard-normal draw per sample, scaled by the predictive std at each point."""
        mean, var = self._predict(x)
        eps = torch.randn(n, x.shape[0], 1, x.shape[-1], generator=generator, dtype=x.dtype, device=x.device)
        return mean + var.sqrt() * eps

    # ------------------------------------------------------------------ helpers
    def _flatten(self, x, name: str = "x") -> tuple[torch.Tensor, torch.Size]:
        """Reshape a query to ``[B, M, D]`` and return the shape the result must take."""
        if not self.fitted:
            raise RuntimeError(f"{type(self).__name__} is not fitted: call fit(source, target) first")
        x = as_float_tensor(x, name, like=self._source)
        if x.ndim == 0 or x.shape[-1] != self.dim:
            raise ValueError(f"{name} must have shape [..., {self.dim}]; got {tuple(x.shape)}")
        check_finite(x, name)
        s = self.batch_shape
        k = len(s)
        if k == 0:
            return x.reshape(1, -1, self.dim), x.shape
        if x.shape[:k] == s:
            return x.reshape(s.numel(), -1, self.dim), x.shape
        flat = x.reshape(1, -1, self.dim).expand(s.numel(), -1, -1)
        return flat, torch.Size((*s, *x.shape))


def jacobian_autograd(f, x: torch.Tensor) -> torch.Tensor:
    """Jacobian of a point-wise map ``f: [B, M, D] -> [B, M, D]`` by D reverse passes: ``[B, M, D, D]``.

    Valid because output point m depends only on input point m, so the gradient of sum_m f_i(x_m) with
    respect to x_m is row i of J(x_m).
    """
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        y = f(x)
        rows = [
            torch.autograd.grad(y[..., i].sum(), x, retain_graph=i < y.shape[-1] - 1)[0] for i in range(y.shape[-1])
        ]
    return torch.stack(rows, dim=-2)


def newton_inverse(f, jac, y: torch.Tensor, x0: torch.Tensor, steps: int = 50, tol: float = 1e-10) -> torch.Tensor:
    """Solve f(x) = y point-wise by damped Newton iterations from ``x0`` (for maps without a closed-form
    inverse). Stops early when the largest residual falls below ``tol`` times the scale of ``y``."""
    x = x0
    scale = y.abs().amax().clamp_min(torch.finfo(y.dtype).tiny)  # relative: no absolute floor for small-scale data
    for _ in range(steps):
        r = f(x) - y
        if r.abs().amax() <= tol * scale:
            break
        dx = torch.linalg.solve(jac(x), r.unsqueeze(-1)).squeeze(-1)
        x = x - dx
    return x
