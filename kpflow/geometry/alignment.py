"""The code base's one rigid (Kabsch), similarity (Umeyama) and affine (least squares) fit of two keypoint sets.

A x + t best carrying sources S onto targets T. With centred keypoints X = S - mean(S), Y = T - mean(T) and
H = X^T Y / N = U diag(s) V^T, the rigid and similarity fits are (Umeyama 1991, Eqs. 39-42)

    R = V E U^T,  E = diag(1, ..., 1, sign det(V U^T))   (reflection-safe),
    c = tr(diag(s) E) / (|X|^2 / N)                       (similarity only; c = 1 when rigid),
    A = c R,  t = mean(T) - A mean(S);

the affine fit solves min_{A,t} sum_i |A s_i + t - t_i|^2. In 2-D the rigid R is computed in closed form, as the
turn by theta = atan2(sum_i x_i cross y_i, sum_i x_i . y_i) (no SVD). With per-point weights w_i (normalised to sum
1) every mean and sum over the points above is weighted (Umeyama's weighted form: mean(S) = sum_i w_i s_i,
H = sum_i w_i x_i y_i^T, |X|^2 / N = sum_i w_i |x_i|^2) and the affine fit minimises sum_i w_i |A s_i + t - t_i|^2.

:func:`fit_affine` fits batches of pairs (torch); :func:`planar_turn` is the 2-D rigid fit's angle for one pair of
numpy arrays. :class:`kpflow.maps.affine.AffineMap` is the map of the fit; a compiled form for one unweighted pair,
:func:`kpflow.maps.ilwr_kernels.align`, takes the SVD steps in 2-D too (the two agree to rounding).

Degenerate keypoints: all-coincident sources raise, coincident meaning relative to the keypoints' own magnitude (a
spread within ~1e3 ulps of it; no absolute threshold, and the fit runs in units of the sources' spread, so it does not
depend on their scale). Collinear sources (or coplanar in 3-D) raise for ``kind="affine"`` since A is then
undetermined; for rigid/similarity fits in 3-D collinear keypoints leave the spin about their common line
undetermined and the SVD picks one, deterministically.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch

Kind = Literal["rigid", "similarity", "affine", "translation"]
KINDS = ("rigid", "similarity", "affine", "translation")


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
            raise ValueError(
                f"source keypoints are {shape}: a full affine map is undetermined (use rigid or similarity)"
            )
        ones = torch.ones(b, n, 1, dtype=source.dtype, device=source.device)
        sol = torch.linalg.lstsq(
            weigh(torch.cat([x, ones], -1), 0.5), weigh(y, 0.5)
        ).solution  # [B, D+1, D]: rows sqrt(w_i)
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


def planar_turn(source: np.ndarray, target: np.ndarray) -> float:
    """The angle (radians) of the 2-D rigid fit carrying points ``source [N, 2]`` onto ``target [N, 2]`` (module
    docstring): ``atan2(sum_i x_i cross y_i, sum_i x_i . y_i)`` for the centred points, in float64."""
    x, y = np.asarray(source, np.float64), np.asarray(target, np.float64)
    x, y = x - x.mean(0), y - y.mean(0)
    return float(np.arctan2(np.sum(x[:, 0] * y[:, 1] - x[:, 1] * y[:, 0]), np.sum(x * y)))
