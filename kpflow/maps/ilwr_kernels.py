"""ILWR's fit and forward pass for one keypoint set as fused loops (numba), the CPU fast path of
:class:`~kpflow.maps.ilwr.ILWRMap`.

They compute exactly what :func:`~kpflow.maps.ilwr.fit_steps` and :func:`~kpflow.maps.ilwr.apply_steps` compute
(the same candidates, the same first-minimum choice, the same clamped weights), in one compiled pass instead of
some twenty tensor operations per step: a fit of 30 steps on 25 keypoints is a few hundred microseconds of
arithmetic, which per-operation overhead made milliseconds. Results agree with the torch path to rounding
(``tests/test_ilwr_kernels.py``: 1e-9 in float64). Compiled on first use and cached beside the module.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def _residuals(z, target, r):  # pragma: no cover  (compiled)
    """r = target - z in place; the largest squared residual and its (first) index."""
    worst, p = -1.0, 0
    for i in range(z.shape[0]):
        e = 0.0
        for j in range(z.shape[1]):
            r[i, j] = target[i, j] - z[i, j]
            e += r[i, j] * r[i, j]
        if e > worst:
            worst, p = e, i
    return worst, p


@numba.njit(cache=True)
def _best_candidate(d2, rv, vn2, grid_c, alpha_c, min_exponent):  # pragma: no cover  (compiled)
    """The (first) candidate minimising a^2 |v|^2 sum_i w_i^2 - 2 a sum_i w_i (r_i . v), and that value."""
    best_val, best_idx = np.inf, 0
    for q in range(grid_c.shape[0]):
        nrho2 = max(grid_c[q] / vn2, -1e30)
        sw, sww = 0.0, 0.0
        for i in range(d2.shape[0]):
            w = math.exp(max(d2[i] * nrho2, min_exponent))
            sw += w * rv[i]
            sww += w * w
        loss = -2.0 * alpha_c[q] * sw + alpha_c[q] * alpha_c[q] * sww * vn2
        if loss < best_val:
            best_val, best_idx = loss, q
    return best_val, best_idx


@numba.njit(cache=True)
def fit_steps(z, target, n_steps, beta, grid_c, alpha_c, tol, tiny, min_exponent):  # pragma: no cover  (compiled)
    """Greedy ILWR fit of ``z [N, D]`` towards ``target [N, D]`` (see :func:`kpflow.maps.ilwr.fit_steps`):
    centres ``[K, D]``, vectors ``[K, D]``, -rho^2 ``[K]`` and the fitted keypoints (K <= n_steps)."""
    n, d = z.shape
    z = z.copy()
    centres = np.zeros((n_steps, d), z.dtype)
    vectors = np.zeros((n_steps, d), z.dtype)
    rhos = np.zeros(n_steps, z.dtype)
    r = np.empty((n, d), z.dtype)
    d2 = np.empty(n, z.dtype)
    rv = np.empty(n, z.dtype)
    c = np.empty(d, z.dtype)
    v = np.empty(d, z.dtype)
    k_done = 0
    for k in range(n_steps):
        worst, p = _residuals(z, target, r)
        if tol > 0 and k > 0 and worst <= tol * tol:
            break
        vn2 = 0.0
        for j in range(d):
            c[j] = z[p, j]
            v[j] = r[p, j] * beta
            vn2 += v[j] * v[j]
        vn2 = max(vn2, tiny)
        for i in range(n):
            s, t = 0.0, 0.0
            for j in range(d):
                s += (z[i, j] - c[j]) ** 2
                t += v[j] * r[i, j]
            d2[i], rv[i] = s, t
        best_val, best_idx = _best_candidate(d2, rv, vn2, grid_c, alpha_c, min_exponent)
        best = max(grid_c[best_idx] / vn2, -1e30)
        scale = alpha_c[best_idx] if best_val < 0 else 0.0
        for j in range(d):
            v[j] *= scale
        for i in range(n):
            w = math.exp(max(d2[i] * best, min_exponent))
            for j in range(d):
                z[i, j] += w * v[j]
        centres[k], vectors[k], rhos[k] = c, v, best
        k_done = k + 1
    return centres[:k_done], vectors[:k_done], rhos[:k_done], z


@numba.njit(cache=True)
def apply_steps(x, centres, vectors, neg_rho2, min_exponent):  # pragma: no cover  (compiled)
    """psi_K o ... o psi_1 (x) for ``x [M, D]`` (see :func:`kpflow.maps.ilwr.apply_steps`)."""
    m, d = x.shape
    out = x.copy()
    for i in range(m):
        for k in range(centres.shape[0]):
            s = 0.0
            for j in range(d):
                s += (out[i, j] - centres[k, j]) ** 2
            w = math.exp(max(s * neg_rho2[k], min_exponent))
            for j in range(d):
                out[i, j] += w * vectors[k, j]
    return out
