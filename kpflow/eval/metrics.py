"""Trajectory metrics.

Curves are tensors ``[..., T, D]`` (T points in D dimensions; leading dimensions
are batch dimensions and broadcast between the two arguments). Numpy arrays are
accepted and converted with :func:`torch.as_tensor`. Integer inputs are promoted
to the default float dtype; float32 and float64 are kept.

* :func:`discrete_frechet` -- discrete Fréchet distance (Eiter & Mannila 1994).
* :func:`dtw` -- dynamic time warping distance (sum of Euclidean distances).
* :func:`final_position_error` -- distance between the last points.
* :func:`rotation_angle_error` -- geodesic angle between rotation matrices.
* :func:`band_coverage` -- share of points inside a k-sigma band.
"""

from __future__ import annotations

import torch

__all__ = [
    "discrete_frechet",
    "dtw",
    "final_position_error",
    "rotation_angle_error",
    "band_coverage",
]


def _as_float(x, name: str) -> torch.Tensor:
    x = torch.as_tensor(x)
    if not (x.is_floating_point() or x.is_complex()):
        x = x.to(torch.get_default_dtype())
    if x.is_complex():
        raise ValueError(f"{name} must be real, got dtype {x.dtype}")
    if torch.isnan(x).any():
        raise ValueError(f"{name} contains NaN")
    return x


def _curves(a, b) -> tuple[torch.Tensor, torch.Tensor]:
    a = _as_float(a, "a")
    b = _as_float(b, "b")
    for name, c in (("a", a), ("b", b)):
        if c.ndim < 2:
            raise ValueError(f"{name} must be a curve [..., T, D], got shape {tuple(c.shape)}")
        if c.shape[-2] == 0:
            raise ValueError(f"{name} must have at least one point, got shape {tuple(c.shape)}")
        if not torch.isfinite(c).all():
            raise ValueError(f"{name} contains inf")
    if a.shape[-1] != b.shape[-1]:
        raise ValueError(f"a and b must have the same point dimension D, got {a.shape[-1]} and {b.shape[-1]}")
    dtype = torch.promote_types(a.dtype, b.dtype)
    a, b = a.to(dtype), b.to(dtype)
    try:
        torch.broadcast_shapes(a.shape[:-2], b.shape[:-2])
    except RuntimeError as err:
        raise ValueError(
            f"batch dimensions of a {tuple(a.shape[:-2])} and b {tuple(b.shape[:-2])} do not broadcast"
        ) from err
    return a, b


def _pairwise(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Euclidean distance matrix ``d[..., i, j] = |a_i - b_j|``, shape [..., T, S]."""
    return torch.linalg.vector_norm(a[..., :, None, :] - b[..., None, :, :], dim=-1)


def _coupling_dp(d: torch.Tensor, combine) -> torch.Tensor:
    """Solve ``c[i,j] = combine(d[i,j], min(c[i-1,j], c[i,j-1], c[i-1,j-1]))`` with c[0,0] = d[0,0].

    The recursion runs over anti-diagonals ``k = i + j``; every cell of one anti-diagonal
    depends only on the two previous ones, so each step is a vectorised op over the
    diagonal (and over the batch). No in-place writes, so the result is differentiable.

    Diagonals are stored as vectors indexed by the row ``i`` of a matrix padded with a
    leading row and column (``C[0,0] = 0``, rest of the border ``inf``): ``diag_k[i] = C[i, k-i]``.
    """
    *batch, T, S = d.shape
    inf = torch.tensor(float("inf"), dtype=d.dtype, device=d.device)
    # Padded distances Dp[i, j] = d[i-1, j-1] (inf on the border), skewed so that
    # skew[k, i] = Dp[i, k - i] (inf where k - i is out of range).
    dp = torch.nn.functional.pad(d, (1, 0, 1, 0), value=float("inf"))
    k = torch.arange(T + S + 1, device=d.device)[:, None]
    i = torch.arange(T + 1, device=d.device)[None, :]
    j = k - i
    valid = (j >= 0) & (j <= S)
    skew = dp[..., i.expand(T + S + 1, T + 1), j.clamp(0, S)]
    skew = torch.where(valid, skew, inf)  # [..., T+S+1, T+1]

    def shift(v):  # shift(v)[i] = v[i-1], inf at i = 0
        return torch.nn.functional.pad(v[..., :-1], (1, 0), value=float("inf"))

    prev2 = torch.full((*batch, T + 1), float("inf"), dtype=d.dtype, device=d.device)
    prev2 = torch.cat([torch.zeros_like(prev2[..., :1]), prev2[..., 1:]], dim=-1)  # diag 0: C[0,0]=0
    prev1 = torch.full_like(prev2, float("inf"))  # diag 1: C[0,1], C[1,0] are border cells
    for kk in range(2, T + S + 1):
        best = torch.minimum(torch.minimum(shift(prev1), prev1), shift(prev2))
        cur = combine(skew[..., kk, :], best)
        prev2, prev1 = prev1, cur
    return prev1[..., T]


def discrete_frechet(a, b) -> torch.Tensor:
    """Discrete Fréchet distance between curves ``a`` [..., T, D] and ``b`` [..., S, D].

    Eiter & Mannila (1994): with ``d(i, j) = |a_i - b_j|``,

        c(0, 0) = d(0, 0)
        c(i, j) = max(d(i, j), min(c(i-1, j), c(i-1, j-1), c(i, j-1)))

    (terms with a negative index are +inf) and the distance is ``c(T-1, S-1)``: the
    smallest, over monotone couplings of the two point sequences, of the largest
    coupled distance. Returns a tensor of shape ``[...]``.
    """
    a, b = _curves(a, b)
    return _coupling_dp(_pairwise(a, b), torch.maximum)


def dtw(a, b) -> torch.Tensor:
    """Dynamic time warping distance between ``a`` [..., T, D] and ``b`` [..., S, D].

    With ``d(i, j) = |a_i - b_j|`` (Euclidean),

        c(0, 0) = d(0, 0)
        c(i, j) = d(i, j) + min(c(i-1, j), c(i-1, j-1), c(i, j-1))

    and the distance is ``c(T-1, S-1)``: the smallest, over monotone couplings, of the
    sum of coupled distances (not normalised by the path length; a curve against its
    translate by ``delta`` perpendicular to it gives ``T * |delta|``). Returns ``[...]``.
    """
    a, b = _curves(a, b)
    return _coupling_dp(_pairwise(a, b), torch.add)


def final_position_error(a, b) -> torch.Tensor:
    """Distance between the last points: ``|a[..., -1, :] - b[..., -1, :]|``, shape ``[...]``."""
    a, b = _curves(a, b)
    return torch.linalg.vector_norm(a[..., -1, :] - b[..., -1, :], dim=-1)


def rotation_angle_error(Ra, Rb) -> torch.Tensor:
    """Geodesic angle (radians, in [0, pi]) between rotations ``Ra``, ``Rb`` [..., D, D], D = 2 or 3.

    With ``R = Ra^T Rb``:

    * 2-D: ``theta = |atan2(R[1,0] - R[0,1], R[0,0] + R[1,1])|``;
    * 3-D: ``theta = arccos((trace(R) - 1) / 2)``, evaluated in the equivalent and
      numerically safe form ``atan2(|w|, (trace(R) - 1) / 2)`` where
      ``w = (R[2,1]-R[1,2], R[0,2]-R[2,0], R[1,0]-R[0,1]) / 2`` has norm ``sin(theta)``
      (no arccos of a value that rounding pushed past +-1; accurate near 0 and pi).

    The inputs are not checked for orthogonality.
    """
    Ra = _as_float(Ra, "Ra")
    Rb = _as_float(Rb, "Rb")
    for name, R in (("Ra", Ra), ("Rb", Rb)):
        if R.ndim < 2 or R.shape[-1] != R.shape[-2] or R.shape[-1] not in (2, 3):
            raise ValueError(f"{name} must have shape [..., D, D] with D = 2 or 3, got {tuple(R.shape)}")
    if Ra.shape[-1] != Rb.shape[-1]:
        raise ValueError(f"Ra and Rb must have the same D, got {Ra.shape[-1]} and {Rb.shape[-1]}")
    dtype = torch.promote_types(Ra.dtype, Rb.dtype)
    R = Ra.to(dtype).transpose(-1, -2) @ Rb.to(dtype)
    if R.shape[-1] == 2:
        return torch.atan2(R[..., 1, 0] - R[..., 0, 1], R[..., 0, 0] + R[..., 1, 1]).abs()
    w = 0.5 * torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], dim=-1
    )
    cos = 0.5 * (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0)
    return torch.atan2(torch.linalg.vector_norm(w, dim=-1), cos.clamp(-1.0, 1.0))


def band_coverage(mean, std, truth, k: float = 2.0) -> torch.Tensor:
    """Share of points whose ``truth`` lies inside the ``k``-sigma band around ``mean``.

    ``mean`` and ``truth`` are [..., T, D]; ``std`` is [..., T, D] (per coordinate) or
    [..., T] (one isotropic std per point, applied to every coordinate). Point t is
    inside when ``|truth[t, d] - mean[t, d]| <= k * std[t, d]`` for *every* coordinate
    d (a box, not an ellipse), and the result is ``(1/T) * sum_t inside_t``, a float
    in [0, 1] of shape ``[...]``.
    """
    mean = _as_float(mean, "mean")
    std = _as_float(std, "std")
    truth = _as_float(truth, "truth")
    if mean.ndim < 2:
        raise ValueError(f"mean must have shape [..., T, D], got {tuple(mean.shape)}")
    if truth.shape != mean.shape:
        raise ValueError(f"truth must have the shape of mean {tuple(mean.shape)}, got {tuple(truth.shape)}")
    if std.shape == mean.shape[:-1]:
        std = std[..., None]
    elif std.shape != mean.shape:
        raise ValueError(f"std must have shape {tuple(mean.shape)} or {tuple(mean.shape[:-1])}, got {tuple(std.shape)}")
    if (std < 0).any():
        raise ValueError("std must be non-negative")
    if not k > 0:
        raise ValueError(f"k must be positive, got {k}")
    dtype = torch.promote_types(torch.promote_types(mean.dtype, std.dtype), truth.dtype)
    inside = ((truth.to(dtype) - mean.to(dtype)).abs() <= k * std.to(dtype)).all(dim=-1)
    return inside.to(dtype).mean(dim=-1)
