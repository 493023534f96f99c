"""Iterative locally weighted translations (ILWR; Perrin & Schlehuber-Caissier 2016, "Fast diffeomorphic
matching to learn globally asymptotically stable nonlinear dynamical systems", Algorithm 1).

On top of an optional affine alignment A, phi = psi_K o ... o psi_1 o A with K steps

    psi_k(x) = x + exp(-rho_k^2 |x - c_k|^2) v_k,                                   (Eq. 3)

where c_k is the currently worst-matched keypoint z_p (z = psi_{k-1} o ... o A applied to the sources),
v_k = alpha beta (target_p - z_p), and (rho_k, alpha) minimise sum_i |target_i - psi_k(z_i)|^2 over
0 < rho_k <= margin * sqrt(e/2) / |v_k| and alpha in {1, 1/2, 1/4, 1/8} (shorter steps may be narrower, which
keeps a step from dragging neighbours the wrong way; a step no candidate improves is skipped). That bound is what keeps every step a diffeomorphism: along v the
step's derivative is 1 - 2 rho^2 |v| s exp(-rho^2 s^2) >= 1 - sqrt(2/e) rho |v| > 0 (Eq. 5), and across v it
is the identity. rho_k is chosen by a vectorised search over a geometric grid of candidates, all keypoint sets
of a batch at once, instead of a general-purpose optimiser per step.

Inverse: psi_k moves points only along v_k, so x = y - t v_k with t = exp(-rho_k^2 |y - t v_k - c_k|^2), a
scalar equation whose left-minus-right side is increasing in t on [0, 1]; it is solved by safeguarded Newton
iterations (at most ``inverse_iters``, fewer once every residual is below ``INVERSE_TOL``), steps undone in reverse
order.

Jacobian: J_k(x) = I - 2 rho_k^2 w_k(x) v_k (x - c_k)^T, chained through the steps and A.

Uncertainty (a heuristic, not a posterior): var(x) = s^2 (1 - k(x)^T (K + lambda I)^-1 k(x)) per coordinate with an
RBF kernel of length-scale l on the source keypoints, s^2 the mean squared non-rigid displacement per coordinate
and l the median step width 1/rho_k. It is ~0 at the keypoints and grows to s^2 away from them.
"""

from __future__ import annotations

import math

import torch

from kpflow.maps import ilwr_kernels
from kpflow.maps.affine import AlignedMap

SQRT_E_2 = math.sqrt(math.e / 2.0)
#: exponents below this are clamped: exp(-80) ~ 2e-35 is a normal float32, while smaller results are subnormal
#: numbers, which CPUs compute up to 50x slower. The weights this drops are below 1e-34.
MIN_EXPONENT = -80.0
#: the inverse's Newton iterations stop once every residual |t - w(t)| of a step is below this
INVERSE_TOL = 1e-13


def weight(exponent: torch.Tensor) -> torch.Tensor:
    """exp(exponent) with the exponent clamped at ``MIN_EXPONENT`` (used identically by fit, forward, inverse
    and Jacobian, so they stay consistent)."""
    return torch.exp(exponent.clamp_min(MIN_EXPONENT))


class ILWRMap(AlignedMap):
    """Diffeomorphic map from K locally weighted translations (module docstring). Batched fits supported.

    Args:
        n_steps: number of translations K.
        beta: fraction of the worst residual each step removes (0 < beta <= 1).
        alignment: prior affine fit ``"rigid"``, ``"similarity"``, ``"affine"``, ``"translation"`` or ``"none"``.
        n_rho: number of candidate widths searched per step.
        margin: safety factor (< 1) on the diffeomorphism bound rho |v| < sqrt(e/2).
        tol: stop early once every keypoint is within ``tol`` (absolute) of its target.
        inverse_iters: Newton iterations per step of the inverse.
        fused: fit and transport one keypoint set on the CPU with the compiled kernels of :mod:`.ilwr_kernels`
            (the same numbers as the torch path, to rounding, several times faster); False: always torch.
    """

    supports_batch = True

    def __init__(
        self,
        n_steps: int = 30,
        beta: float = 0.9,
        alignment: str = "rigid",
        n_rho: int = 16,
        margin: float = 0.99,
        tol: float = 0.0,
        inverse_iters: int = 12,
        uncertainty_scale: float | None = None,
        fused: bool = True,
    ) -> None:
        super().__init__(alignment)
        self.fused = bool(fused)
        if not 0.0 < beta <= 1.0:
            raise ValueError(f"beta must be in (0, 1]; got {beta}")
        if not 0.0 < margin < 1.0:
            raise ValueError(f"margin must be in (0, 1); got {margin}")
        if n_steps < 1 or n_rho < 2:
            raise ValueError(f"need n_steps >= 1 and n_rho >= 2; got {n_steps}, {n_rho}")
        self.n_steps, self.beta, self.n_rho, self.margin = n_steps, beta, n_rho, margin
        self.tol, self.inverse_iters, self.uncertainty_scale = tol, inverse_iters, uncertainty_scale
        for name in ("centres", "vectors", "neg_rho2", "_chol", "_s2", "_ell2"):
            self.register_buffer(name, None)

    # ------------------------------------------------------------------ fit
    def _fit(self, source: torch.Tensor, target: torch.Tensor) -> None:
        self._chol = None  # the uncertainty model is built on first use (predict/sample)
        if self._fused(source) and not target.requires_grad:
            compiled = self.alignment.kind in ilwr_kernels.ALIGN_KINDS  # the kernels fit these; torch the affine one
            if not compiled:
                self._fit_alignment(source, target)
            if not compiled or self._fit_alignment_compiled(source, target):  # declined: the torch path below
                grid = self._width_grid(torch.float64, source.device)
                self.centres, self.vectors, self.neg_rho2 = _fit_steps_fused(
                    source, target, self.alignment, self.n_steps, self.beta, grid, self.tol
                )
                return
        self._fit_alignment(source, target)
        z = self.alignment._forward(source)
        grid = self._width_grid(source.dtype, source.device)
        self.centres, self.vectors, self.neg_rho2, z = fit_steps(z, target, self.n_steps, self.beta, grid, self.tol)

    def _width_grid(self, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
        """The searched widths as -(rho |v|)^2: ``n_rho`` values geometric up to the diffeomorphism bound."""
        return -((self.margin * SQRT_E_2) ** 2) * torch.logspace(-4, 0, self.n_rho, dtype=dtype, device=device)

    def _fused(self, x: torch.Tensor) -> bool:
        """Whether the compiled kernels (:mod:`.ilwr_kernels`) take this call: one keypoint set on the CPU in
        float64, no autograd graph wanted; ``fused=False`` keeps the torch path. Float32 stays on torch, so that a
        float32 batch and the same sets fitted one by one give the same maps (the kernels sum in float64, which
        picks other steps than torch's float32 arithmetic in near ties: up to 0.2 px apart on the benchmark)."""
        return (self.fused and x.shape[0] == 1 and x.device.type == "cpu" and x.dtype == torch.float64
                and not (torch.is_grad_enabled() and x.requires_grad))  # fmt: skip

    def _fit_uncertainty(self) -> None:
        n, d = self._source.shape[-2:]
        source, target = self._source.reshape(-1, n, d), self._target.reshape(-1, n, d)
        base = self.alignment._forward(source)
        if self.uncertainty_scale is not None:
            s2 = torch.full(
                source.shape[:1], float(self.uncertainty_scale) ** 2, dtype=source.dtype, device=source.device
            )
        else:
            s2 = (target - base).square().mean((1, 2))
        width2 = 1.0 / (-self.neg_rho2).clamp_min(torch.finfo(source.dtype).tiny)  # [B, K]
        ell2 = width2.median(dim=1).values
        spread2 = (source - source.mean(1, keepdim=True)).square().sum(-1).mean(1)
        ell2 = torch.minimum(ell2, spread2).clamp_min(1e-12 * spread2.clamp_min(1e-30))
        k = torch.exp(-0.5 * torch.cdist(source, source).square() / ell2[:, None, None])
        k = k + 1e-6 * torch.eye(source.shape[1], dtype=source.dtype, device=source.device)
        self._chol, self._s2, self._ell2 = torch.linalg.cholesky(k), s2, ell2

    # ------------------------------------------------------------------ evaluate
    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        if self._fused(x) and not any(
            p.requires_grad for p in (self.centres, self.vectors, self.neg_rho2, self.alignment.A, self.alignment.t)
        ):
            al = self.alignment
            z = ilwr_kernels.apply_affine(x[0].numpy(), al.A[0].numpy(), al.t[0].numpy())
            out = ilwr_kernels.apply_steps(
                z, self.centres[0].numpy(), self.vectors[0].numpy(), self.neg_rho2[0].numpy(), MIN_EXPONENT
            )
            return torch.from_numpy(out)[None]
        return apply_steps(self.alignment._forward(x), self.centres, self.vectors, self.neg_rho2)

    def _inverse(self, y: torch.Tensor) -> torch.Tensor:
        if self._fused(y) and not any(p.requires_grad for p in (self.centres, self.vectors, self.neg_rho2)):
            x = ilwr_kernels.invert_steps(y[0].numpy(), self.centres[0].numpy(), self.vectors[0].numpy(), self.neg_rho2[0].numpy(),
                                          self.inverse_iters, INVERSE_TOL, MIN_EXPONENT)  # fmt: skip
            return self.alignment._inverse(torch.from_numpy(x)[None])
        x = invert_steps(y, self.centres, self.vectors, self.neg_rho2, self.inverse_iters)
        return self.alignment._inverse(x)

    def _jacobian(self, x: torch.Tensor) -> torch.Tensor:
        if self._fused(x) and not any(
            p.requires_grad for p in (self.centres, self.vectors, self.neg_rho2, self.alignment.A, self.alignment.t)
        ):
            al = self.alignment
            jac = ilwr_kernels.jacobian(x[0].numpy(), al.A[0].numpy(), al.t[0].numpy(), self.centres[0].numpy(), self.vectors[0].numpy(),
                                        self.neg_rho2[0].numpy(), MIN_EXPONENT)  # fmt: skip
            return torch.from_numpy(jac)[None]
        b, m, d = x.shape
        jac = self.alignment.A[:, None].expand(b, m, d, d)
        x = self.alignment._forward(x)
        for k in range(self.centres.shape[1]):
            c, v, nr2 = self.centres[:, k, None], self.vectors[:, k, None], self.neg_rho2[:, k, None, None]
            diff = x - c
            w = weight(nr2 * diff.square().sum(-1, keepdim=True))  # [B, M, 1]
            # J_k = I + 2 (-rho^2) w v diff^T ;  J <- J_k J = J + 2 (-rho^2) w v (diff^T J)
            row = diff[..., None, :] @ jac  # [B, M, 1, D]
            live = w > math.exp(MIN_EXPONENT)  # the clamped weight is constant there: zero derivative
            jac = jac + (2 * nr2 * w * live)[..., None] * v[..., :, None] * row
            x = x + w * v
        return jac

    def _predict(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self._chol is None:
            self._fit_uncertainty()
        kx = torch.exp(
            -0.5
            * torch.cdist(x, self._source.reshape(-1, *self._source.shape[-2:])).square()
            / self._ell2[:, None, None]
        )
        a = torch.cholesky_solve(kx.transpose(1, 2), self._chol)  # [B, N, M]
        frac = (kx * a.transpose(1, 2)).sum(-1).clamp(0.0, 1.0)  # [B, M]
        var = (self._s2[:, None] * (1.0 - frac))[..., None].expand(-1, -1, x.shape[-1])
        return self._forward(x), var


def step_candidates(neg_grid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The step search's candidates ``[C]``: each step length alpha in (1, 1/2, 1/4, 1/8) with every width of
    ``neg_grid``, as (alpha, -(rho |alpha v|)^2 / alpha^2)."""
    alpha = 0.5 ** torch.arange(ilwr_kernels.N_ALPHA, dtype=neg_grid.dtype, device=neg_grid.device)  # as the kernels
    return alpha.repeat_interleave(neg_grid.shape[0]), (neg_grid[None, :] / alpha[:, None] ** 2).reshape(-1)


def _fit_steps_fused(source: torch.Tensor, target: torch.Tensor, alignment, n_steps: int, beta: float, neg_grid: torch.Tensor,
                     tol: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
    """:func:`fit_steps` for one keypoint set behind its fitted ``alignment`` through the compiled kernels (the same
    formulas, candidates and order): ``(centres, vectors, -rho^2)`` with a leading batch dimension of 1."""
    src, tgt = source[0].detach().numpy(), target[0].detach().numpy()
    z = ilwr_kernels.apply_affine(src, alignment.A[0].detach().numpy(), alignment.t[0].detach().numpy())
    c, v, nr2, _ = ilwr_kernels.fit_steps(
        z, tgt, n_steps, beta, neg_grid.numpy(), tol, torch.finfo(torch.float64).tiny, MIN_EXPONENT
    )
    return tuple(torch.from_numpy(arr)[None] for arr in (c, v, nr2))


def fit_steps(z: torch.Tensor, target: torch.Tensor, n_steps: int, beta: float, neg_grid: torch.Tensor, tol: float):
    """Greedy ILWR fit on ``z [B, N, D]`` towards ``target``; ``neg_grid [G]`` holds -(rho |v|)^2 candidates.

    Each step searches the widths rho for v = beta r_p and for the shortened steps alpha v (alpha in 1/2, 1/4,
    1/8), whose bound sqrt(e/2) / (alpha |v|) allows narrower, more local translations; a step that no
    candidate makes better than doing nothing is skipped (v = 0). The sum of squared keypoint errors therefore
    never increases. Returns centres ``[B, K, D]``, vectors ``[B, K, D]``, -rho^2 ``[B, K]`` and the fitted
    keypoints.
    """
    b, _, d = z.shape
    tiny = torch.finfo(z.dtype).tiny
    alpha_c, grid_c = step_candidates(neg_grid)
    a2, neg_2a = alpha_c * alpha_c, -2.0 * alpha_c
    alpha_b = alpha_c.expand(b, -1)
    zero = z.new_zeros(())
    centres, vectors, rhos = [], [], []
    for k in range(n_steps):
        r = target - z
        err2 = (r * r).sum(-1)  # [B, N]
        if tol > 0 and k > 0 and bool(err2.amax() <= tol * tol):
            break
        p = err2.argmax(-1, keepdim=True).unsqueeze(-1).expand(-1, 1, d)
        c = torch.gather(z, 1, p)  # [B, 1, D]
        v = torch.gather(r, 1, p) * beta
        vn2 = (v * v).sum(-1).clamp_min_(tiny)  # [B, 1]
        diff = z - c
        d2 = (diff * diff).sum(-1, keepdim=True)  # [B, N, 1]
        rv = torch.bmm(v, r.transpose(1, 2))  # [B, 1, N]
        nrho2 = (grid_c / vn2).clamp_min_(-1e30)  # [B, C]; finite even when v = 0
        w = weight(torch.bmm(d2, nrho2.unsqueeze(1)))  # [B, N, C]
        # sum_i |r_i - a w_i v|^2 - |r_i|^2 = a^2 |v|^2 sum_i w_i^2 - 2 a sum_i w_i (r_i . v)
        loss = torch.addcmul(neg_2a * torch.bmm(rv, w).squeeze(1), a2 * (w * w).sum(1), vn2)  # [B, C]
        val, idx = loss.min(-1, keepdim=True)
        best = torch.gather(nrho2, 1, idx)  # [B, 1]
        v = v * torch.where(val < 0, torch.gather(alpha_b, 1, idx), zero).unsqueeze(-1)  # skip if nothing helps
        z = torch.addcmul(z, weight(d2 * best.unsqueeze(1)), v)
        centres.append(c)
        vectors.append(v)
        rhos.append(best)
    return torch.cat(centres, 1), torch.cat(vectors, 1), torch.cat(rhos, 1), z


def apply_steps(x: torch.Tensor, centres: torch.Tensor, vectors: torch.Tensor, neg_rho2: torch.Tensor) -> torch.Tensor:
    """psi_K o ... o psi_1 (x) for ``x [B, M, D]`` (Eq. 3)."""
    for k in range(centres.shape[1]):
        d2 = (x - centres[:, k, None]).square_().sum(-1, keepdim=True)
        x = torch.addcmul(x, weight(d2 * neg_rho2[:, k, None, None]), vectors[:, k, None])
    return x


def invert_steps(
    y: torch.Tensor, centres: torch.Tensor, vectors: torch.Tensor, neg_rho2: torch.Tensor, iters: int
) -> torch.Tensor:
    """Undo the steps in reverse order; each one by solving g(t) = t - exp(-rho^2 |y - c - t v|^2) = 0 on [0, 1]."""
    for k in reversed(range(centres.shape[1])):
        v = vectors[:, k, None]  # [B, 1, D]
        nr2 = neg_rho2[:, k, None]  # [B, 1]
        dy = y - centres[:, k, None]
        a = dy.square().sum(-1)  # |d|^2          [B, M]
        b = (dy * v).sum(-1)  # d . v
        c = v.square().sum(-1)  # |v|^2          [B, 1]
        lo, hi = torch.zeros_like(a), torch.ones_like(a)
        t = weight(nr2 * a)  # first guess: the weight at y
        for _ in range(iters):
            expo = nr2 * (a - 2 * t * b + t * t * c)
            e = weight(expo)
            g = t - e
            if bool(g.abs().amax() <= INVERSE_TOL):  # converged (Newton's quadratic rate: usually 3-5 iterations)
                break
            lo = torch.where(g < 0, t, lo)
            hi = torch.where(g >= 0, t, hi)
            dg = 1.0 - (expo > MIN_EXPONENT) * e * nr2 * (2 * t * c - 2 * b)  # > 0 for a diffeomorphic step
            t_new = t - g / dg
            t = torch.where((t_new >= lo) & (t_new <= hi), t_new, 0.5 * (lo + hi))
        y = y - t[..., None] * v
    return y
