"""Affine transportation maps: rigid (Kabsch), similarity (Umeyama) and full affine (least squares).

phi(x) = A x + t. With centred keypoints X = S - mean(S), Y = T - mean(T) and H = X^T Y / N = U diag(s) V^T,
the rigid and similarity fits are (Umeyama 1991, Eqs. 39-42)

    R = V E U^T,  E = diag(1, ..., 1, sign det(V U^T))   (reflection-safe),
    c = tr(diag(s) E) / (|X|^2 / N)                       (similarity only; c = 1 when rigid),
    A = c R,  t = mean(T) - A mean(S);

the affine fit solves min_{A,t} sum_i |A s_i + t - t_i|^2. In 2-D the rigid R is computed in closed form, as the
turn by theta = atan2(sum_i x_i cross y_i, sum_i x_i . y_i) (no SVD). With per-point weights w_i (normalised to sum
1) every mean and sum over the points above is weighted (Umeyama's weighted form: mean(S) = sum_i w_i s_i,
H = sum_i w_i x_i y_i^T, |X|^2 / N = sum_i w_i |x_i|^2) and the affine fit minimises sum_i w_i |A s_i + t - t_i|^2.

:func:`fit_affine` is the code base's one rigid (Kabsch), similarity and affine fit. Its compiled form for one
unweighted pair, :func:`kpflow.maps.ilwr_kernels.align` (the fast path of :class:`AlignedMap`), takes the SVD steps
in 2-D too; the two agree to rounding.

Degenerate keypoints: all-coincident sources raise, coincident meaning relative to the keypoints' own magnitude (a
spread within ~1e3 ulps of it; no absolute threshold, and the fit runs in units of the sources' spread, so it does not
depend on their scale). Collinear sources (or coplanar in 3-D) raise for ``kind="affine"`` since A is then
undetermined; for rigid/similarity fits in 3-D collinear keypoints leave the spin about their common line
undetermined and the SVD picks one, deterministically.
"""

from __future__ import annotations

from typing import Literal

import torch

from kpflow.maps import ilwr_kernels
from kpflow.maps.base import TransportMap

Kind = Literal["rigid", "similarity", "affine", "translation"]
KINDS = ("rigid", "similarity", "affine", "translation")


class AffineMap(TransportMap):
    """phi(x) = A x + t fitted by Kabsch (``rigid``), Umeyama (``similarity``), least squares (``affine``),
    or mean displacement (``translation``). Batched fits supported."""

    supports_batch = True

    def __init__(self, kind: Kind = "rigid") -> None:
        super().__init__()
        if kind not in KINDS:
            raise ValueError(f"unknown affine kind {kind!r}; choose one of {KINDS}")
        self.kind = kind
        self.register_buffer("A", None)
        self.register_buffer("t", None)

    def required_points(self, dim: int) -> int:
        return {"translation": 1, "rigid": 2, "similarity": 2}.get(self.kind, dim + 1)

    def _fit(self, source: torch.Tensor, target: torch.Tensor) -> None:
        self.A, self.t = fit_affine(source, target, self.kind)

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.t[:, None, :], x, self.A.transpose(1, 2))

    def _inverse(self, y: torch.Tensor) -> torch.Tensor:
        return torch.linalg.solve(self.A[:, None], (y - self.t[:, None, :]).unsqueeze(-1)).squeeze(-1)

    def _jacobian(self, x: torch.Tensor) -> torch.Tensor:
        return self.A[:, None].expand(-1, x.shape[1], -1, -1)


def fit_affine(
    source: torch.Tensor, target: torch.Tensor, kind: Kind, weights: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form fit on ``[B, N, D]`` pairs; returns ``A [B, D, D]``, ``t [B, D]`` (module docstring).

    ``weights`` ``[B, N]`` or ``[N]`` (finite, >= 0, not all 0 in a set) weigh the points' squared residuals;
    None weighs them equally."""
    b, n, d = source.shape
    w = None
    if weights is not None:
        w = torch.as_tensor(weights, dtype=source.dtype, device=source.device).expand(b, n)
        if not (torch.isfinite(w).all() and (w >= 0).all() and (w.sum(1) > 0).all()):
            raise ValueError("point weights must be finite and >= 0, and not all 0 in a set")
        w = n * w / w.sum(1, keepdim=True)  # mean 1: each weighted mean below is the plain mean of w_i z_i

    def weigh(z: torch.Tensor, power: float = 1.0) -> torch.Tensor:
        """``w_i^power z_i`` for points ``z [B, N, ...]`` (``z`` itself, untouched, without weights)."""
        return z if w is None else z * (w if power == 1.0 else w.pow(power))[..., None]

    mu_s, mu_t = weigh(source).mean(1), weigh(target).mean(1)
    x, y = source - mu_s[:, None], target - mu_t[:, None]
    eye = torch.eye(d, dtype=source.dtype, device=source.device).expand(b, d, d)
    if kind == "translation":
        return eye.clone(), mu_t - mu_s
    # Work in units of the sources' RMS spread (every fit below is invariant to a common scaling of x and y:
    # A is unchanged), so the result does not depend on the keypoints' scale and squares cannot underflow.
    finfo = torch.finfo(source.dtype)
    peak = x.abs().amax((1, 2)).clamp_min(finfo.tiny)  # [B]
    rms = peak * weigh((x / peak[:, None, None]).square()).sum((1, 2)).div(n).sqrt()  # [B]
    # Coincident: the spread is within float resolution of the keypoints' own magnitude (no absolute floor).
    magnitude = source.abs().amax((1, 2))
    flat = rms <= 1e3 * finfo.eps * magnitude
    if flat.any():
        k = int(flat.nonzero()[0, 0])
        raise ValueError(
            f"all source keypoints{'' if w is None else ' of positive weight'} coincide: their spread {float(rms[k]):.3g} is "
            f"within {source.dtype} resolution of their magnitude {float(magnitude[k]):.3g}, so the rotation of the map is undetermined"
        )
    if kind == "rigid" and d == 2:
        return _planar_rigid(x, y, weigh, rms, mu_s, mu_t)
    x, y = x / rms[:, None, None], y / rms[:, None, None]
    spread = weigh(x.square()).sum((1, 2)) / n  # [B], 1 up to rounding
    eps = finfo.eps
    if kind == "affine":
        sv = torch.linalg.svdvals(weigh(x, 0.5))  # [B, D]
        if (sv[:, -1] <= 1e4 * eps * sv[:, 0]).any():
            shape = "collinear" if d == 2 else "coplanar or collinear"
            raise ValueError(f"source keypoints are {shape}: a full affine map is undetermined (use rigid or similarity)")
        ones = torch.ones(b, n, 1, dtype=source.dtype, device=source.device)
        sol = torch.linalg.lstsq(weigh(torch.cat([x, ones], -1), 0.5), weigh(y, 0.5)).solution  # [B, D+1, D]: rows sqrt(w_i)
        a = sol[:, :d].transpose(1, 2)
        return a, mu_t - (a @ mu_s[..., None]).squeeze(-1)
    h = weigh(x).transpose(1, 2) @ y / n  # [B, D, D]
    u, s, vh = torch.linalg.svd(h)
    v = vh.transpose(1, 2)
    sign = torch.linalg.det(v @ u.transpose(1, 2)).sign()
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    e = torch.ones(b, d, dtype=source.dtype, device=source.device)
    e[:, -1] = sign
    r = v @ (e[..., None] * u.transpose(1, 2))
    if kind == "similarity":
        c = (s * e).sum(-1) / spread
        r = c[:, None, None] * r
    return r, mu_t - (r @ mu_s[..., None]).squeeze(-1)


def _planar_rigid(x, y, weigh, rms, mu_s, mu_t) -> tuple[torch.Tensor, torch.Tensor]:
    """The rigid fit in 2-D, in closed form: for D = 2 Umeyama's ``R = V E U^T`` is the turn by
    ``theta = atan2(sum_i w_i x_i cross y_i, sum_i w_i x_i . y_i)`` (centred ``x_i``, ``y_i``). The sums are taken in
    units of the power of two nearest the sources' spread: exact scaling, so the angle is the raw sums' to the bit
    (which the released Push-T K-CFMs' goal frames were trained with) at any scale without under- or overflow."""
    unit = torch.exp2(torch.round(torch.log2(rms)))[:, None, None]
    x, y = weigh(x / unit), y / unit
    cross = (x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]).sum(-1)
    theta = torch.atan2(cross, (x * y).sum((-1, -2)))
    c, s = theta.cos(), theta.sin()
    r = torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)
    return r, mu_t - (r @ mu_s[..., None]).squeeze(-1)


class AlignedMap(TransportMap):
    """Base of the nonlinear families that sit on a prior affine fit ``self.alignment`` (an :class:`AffineMap`;
    ``alignment="none"`` makes it the identity). ``_fit_alignment`` fits it on flat ``[B, N, D]`` pairs."""

    def __init__(self, alignment: str | None = "rigid") -> None:
        super().__init__()
        self.aligned = alignment not in (None, "none")
        self.alignment = AffineMap(alignment if self.aligned else "translation")

    def required_points(self, dim: int) -> int:
        return self.alignment.required_points(dim) if self.aligned else 1

    def _fit_alignment_compiled(self, source: torch.Tensor, target: torch.Tensor) -> bool:
        """Fit a rigid, similarity or translation alignment on float64 CPU ``[B, N, D]`` pairs with the compiled
        kernel (:func:`~kpflow.maps.ilwr_kernels.align`, the same Umeyama steps, one set at a time). Returns False,
        having fitted nothing, where it declines: another kind, coincident sources or an ill-determined rotation
        (the torch fit then raises the error or decides the rotation as a batch would)."""
        kind = self.alignment.kind
        if kind not in ilwr_kernels.ALIGN_KINDS:
            return False
        finfo = torch.finfo(torch.float64)
        fits = []
        for s, t in zip(source.detach().numpy(), (target if self.aligned else source).detach().numpy()):
            a, b, ok = ilwr_kernels.align(s, t, ilwr_kernels.ALIGN_KINDS[kind], finfo.eps, finfo.tiny)
            if not ok:
                return False
            fits.append((torch.from_numpy(a), torch.from_numpy(b)))
        self._fit_alignment(source, target, fitted=(torch.stack([f[0] for f in fits]), torch.stack([f[1] for f in fits])))
        return True

    def _fit_alignment(self, source: torch.Tensor, target: torch.Tensor, fitted: tuple | None = None) -> None:
        """Fit the alignment on ``[B, N, D]`` pairs, or take ``fitted = (A, t)`` computed elsewhere (a compiled path)."""
        al = self.alignment
        al.batch_shape, al.dim, al._source, al._target = torch.Size([source.shape[0]]), source.shape[-1], source, target
        al.A, al.t = fitted if fitted is not None else fit_affine(source, target if self.aligned else source, al.kind)
