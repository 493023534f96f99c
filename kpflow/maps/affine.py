"""Affine transportation maps: phi(x) = A x + t fitted by Kabsch (``rigid``), Umeyama (``similarity``), least squares
(``affine``) or the mean displacement (``translation``), and the nonlinear families' prior fit (:class:`AlignedMap`).

The fits are :func:`kpflow.geometry.alignment.fit_affine` (the formulas are there), the code base's one rigid,
similarity and affine fit. Its compiled form for one unweighted pair, :func:`kpflow.maps.ilwr_kernels.align` (the
fast path of :class:`AlignedMap`), takes the SVD steps in 2-D too; the two agree to rounding.
"""

from __future__ import annotations

import torch

from kpflow.geometry.alignment import KINDS, Kind, fit_affine
from kpflow.maps import ilwr_kernels
from kpflow.maps.base import TransportMap


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
        self._fit_alignment(
            source, target, fitted=(torch.stack([f[0] for f in fits]), torch.stack([f[1] for f in fits]))
        )
        return True

    def _fit_alignment(self, source: torch.Tensor, target: torch.Tensor, fitted: tuple | None = None) -> None:
        """Fit the alignment on ``[B, N, D]`` pairs, or take ``fitted = (A, t)`` computed elsewhere (a compiled path)."""
        al = self.alignment
        al.batch_shape, al.dim, al._source, al._target = torch.Size([source.shape[0]]), source.shape[-1], source, target
        al.A, al.t = fitted if fitted is not None else fit_affine(source, target if self.aligned else source, al.kind)
