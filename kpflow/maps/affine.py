"""Affine transportation maps: rigid (Kabsch), similarity (Umeyama) and full affine (least squares).

phi(x) = A x + t. With centred keypoints X = S - mean(S), Y = T - mean(T) and H = X^T Y / N = U diag(s) V^T,
the rigid and similarity fits are (Umeyama 1991, Eqs. 39-42)

    R = V E U^T,  E = diag(1, ..., 1, sign det(V U^T))   (reflection-safe),
    c = tr(diag(s) E) / (|X|^2 / N)                       (similarity only; c = 1 when rigid),
    A = c R,  t = mean(T) - A mean(S);

the affine fit solves min_{A,t} sum_i |A s_i + t - t_i|^2.

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


def fit_affine(source: torch.Tensor, target: torch.Tensor, kind: Kind) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form fit on ``[B, N, D]`` pairs; returns ``A [B, D, D]``, ``t [B, D]`` (module docstring)."""
    b, n, d = source.shape
    mu_s, mu_t = source.mean(1), target.mean(1)
    x, y = source - mu_s[:, None], target - mu_t[:, None]
    eye = torch.eye(d, dtype=source.dtype, device=source.device).expand(b, d, d)
    if kind == "translation":
        return eye.clone(), mu_t - mu_s
    # Work in units of the sources' RMS spread (every fit below is invariant to a common scaling of x and y:
    # A is unchanged), so the result does not depend on the keypoints' scale and squares cannot underflow.
    finfo = torch.finfo(source.dtype)
    peak = x.abs().amax((1, 2)).clamp_min(finfo.tiny)  # [B]
    rms = peak * (x / peak[:, None, None]).square().sum((1, 2)).div(n).sqrt()  # [B]
    # Coincident: the spread is within float resolution of the keypoints' own magnitude (no absolute floor).
    magnitude = source.abs().amax((1, 2))
    flat = rms <= 1e3 * finfo.eps * magnitude
    if flat.any():
        k = int(flat.nonzero()[0, 0])
        raise ValueError(
            f"all source keypoints coincide: their spread {float(rms[k]):.3g} is within {source.dtype} resolution "
            f"of their magnitude {float(magnitude[k]):.3g}, so the rotation of the map is undetermined"
        )
    x, y = x / rms[:, None, None], y / rms[:, None, None]
    spread = x.square().sum((1, 2)) / n  # [B], 1 up to rounding
    eps = finfo.eps
    if kind == "affine":
        sv = torch.linalg.svdvals(x)  # [B, D]
        if (sv[:, -1] <= 1e4 * eps * sv[:, 0]).any():
            shape = "collinear" if d == 2 else "coplanar or collinear"
            raise ValueError(f"source keypoints are {shape}: a full affine map is undetermined (use rigid or similarity)")
        ones = torch.ones(b, n, 1, dtype=source.dtype, device=source.device)
        sol = torch.linalg.lstsq(torch.cat([x, ones], -1), y).solution  # [B, D+1, D]
        a = sol[:, :d].transpose(1, 2)
        return a, mu_t - (a @ mu_s[..., None]).squeeze(-1)
    h = x.transpose(1, 2) @ y / n  # [B, D, D]
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
