"""ILWR's fit, forward pass, inverse and Jacobian for one keypoint set as fused loops (numba), the CPU fast path of
:class:`~kpflow.maps.ilwr.ILWRMap`.

They compute what :func:`~kpflow.geometry.alignment.fit_affine` (rigid, similarity, translation),
:func:`~kpflow.maps.ilwr.fit_steps`, :func:`~kpflow.maps.ilwr.apply_steps`, :func:`~kpflow.maps.ilwr.invert_steps` and
the Jacobian compute (the same candidates, the same
first-minimum choice, the same clamped weights), in float64, in a few compiled passes instead of some twenty tensor
operations per step: a fit of 30 steps on 25 keypoints is about 150 microseconds of arithmetic, which per-operation
overhead made milliseconds. Results agree with the torch path to rounding (``tests/test_ilwr_kernels.py``: 1e-9 in
float64). Compiled on first use and cached beside the module.
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


#: the step lengths alpha of the search, 2^-b for b < N_ALPHA (:func:`kpflow.maps.ilwr.step_candidates`)
N_ALPHA = 4


@numba.njit(cache=True)
def _best_candidate(d2, rv, vn2, neg_grid, min_exponent):  # pragma: no cover  (compiled)
    """The (first) candidate q = b G + g minimising a^2 |v|^2 sum_i w_i^2 - 2 a sum_i w_i (r_i . v), with
    a = 2^-b and w_i = exp(d2_i 4^b neg_grid[g] / |v|^2) (clamped), and that value.

    The candidates are :func:`kpflow.maps.ilwr.step_candidates`' in its order. Their exponents for one width are
    e, 4 e, 16 e, 64 e (scalings by powers of two, exact), so one exp and repeated squaring give all four
    weights: a quarter of the exps, which are this search's cost, at a relative difference of at most ~100 ulps
    (each squaring doubles it).
    """
    n_grid = neg_grid.shape[0]
    sw = np.zeros(N_ALPHA * n_grid)
    sww = np.zeros(N_ALPHA * n_grid)
    floor = math.exp(min_exponent)  # the weight of a clamped exponent
    nrho2 = np.empty(N_ALPHA)
    for g in range(n_grid):
        squaring = True  # the widths, clamped as the torch path clamps them; squaring needs them exact multiples
        for b in range(N_ALPHA):
            nrho2[b] = max(neg_grid[g] * 4.0**b / vn2, -1e30)
            squaring = squaring and nrho2[b] == nrho2[0] * 4.0**b
        for i in range(d2.shape[0]):
            e = d2[i] * nrho2[0]
            w = math.exp(e) if e > min_exponent else floor
            for b in range(N_ALPHA):
                if b > 0:
                    if squaring:
                        e *= 4.0
                        w = w * w
                        w = w * w if e > min_exponent else floor
                    else:  # |v| ~ 0 clamped a width: each weight directly
                        e = d2[i] * nrho2[b]
                        w = math.exp(e) if e > min_exponent else floor
                q = b * n_grid + g
                sw[q] += w * rv[i]
                sww[q] += w * w
    best_val, best_idx = np.inf, 0
    for q in range(N_ALPHA * n_grid):
        a = 0.5 ** (q // n_grid)
        loss = -2.0 * a * sw[q] + a * a * sww[q] * vn2
        if loss < best_val:
            best_val, best_idx = loss, q
    return best_val, best_idx


@numba.njit(cache=True)
def fit_steps(z, target, n_steps, beta, neg_grid, tol, tiny, min_exponent):  # pragma: no cover  (compiled)
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
        best_val, best_idx = _best_candidate(d2, rv, vn2, neg_grid, min_exponent)
        b, g = divmod(best_idx, neg_grid.shape[0])
        best = max(neg_grid[g] * 4.0**b / vn2, -1e30)
        scale = 0.5**b if best_val < 0 else 0.0
        for j in range(d):
            v[j] *= scale
        for i in range(n):
            w = math.exp(max(d2[i] * best, min_exponent))
            for j in range(d):
                z[i, j] += w * v[j]
        centres[k], vectors[k], rhos[k] = c, v, best
        k_done = k + 1
    return centres[:k_done], vectors[:k_done], rhos[:k_done], z


#: the alignments :func:`align` computes, by code
ALIGN_KINDS = {"rigid": 0, "similarity": 1, "translation": 2}


@numba.njit(cache=True)
def align(source, target, kind, eps, tiny):  # pragma: no cover  (compiled)
    """The compiled form of :func:`kpflow.geometry.alignment.fit_affine` (unweighted) for one pair ``[N, D]``, the fast path
    of :class:`~kpflow.maps.affine.AlignedMap` (``kind`` a code of ``ALIGN_KINDS``; the same Umeyama steps in units of
    the sources' RMS spread, where ``fit_affine`` turns a 2-D rigid fit by the closed-form angle of the same rotation;
    ``tests/test_ilwr_kernels.py`` checks they agree to rounding): ``(A [D, D], t [D], ok)``. ``ok`` is False where the sources
    coincide or where the rotation is ill-determined (rank of H below D - 1, or a reflection fix between two nearly
    equal singular values: there two SVD implementations may pick different valid rotations); the caller then takes
    the torch path, which raises the error that names the first and decides the second as a batch would."""
    n, d = source.shape
    mu_s, mu_t = np.zeros(d), np.zeros(d)
    for i in range(n):
        for j in range(d):
            mu_s[j] += source[i, j] / n
            mu_t[j] += target[i, j] / n
    a = np.eye(d)
    if kind == 2:
        return a, mu_t - mu_s, True
    x, y = source - mu_s, target - mu_t
    peak = max(np.abs(x).max(), tiny)
    rms = peak * math.sqrt(((x / peak) ** 2).sum() / n)
    if rms <= 1e3 * eps * np.abs(source).max():
        return a, mu_t - mu_s, False
    x, y = x / rms, y / rms
    spread = (x * x).sum() / n
    u, s, vh = np.linalg.svd(x.T @ y / n)
    v = vh.T
    e = np.ones(d)
    reflect = np.linalg.det(v @ u.T) < 0
    if s[0] <= tiny or s[d - 2] <= 1e-6 * s[0] or (reflect and s[d - 2] - s[d - 1] <= 1e-6 * s[0]):
        return a, mu_t - mu_s, False
    if reflect:
        e[d - 1] = -1.0
    r = v @ (np.expand_dims(e, 1) * u.T)
    if kind == 1:
        r = r * ((s * e).sum() / spread)
    return r, mu_t - r @ mu_s, True


@numba.njit(cache=True)
def apply_affine(x, a, t):  # pragma: no cover  (compiled)
    """A x + t for ``x [M, D]``."""
    return x @ a.T + t


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


@numba.njit(cache=True)
def invert_steps(y, centres, vectors, neg_rho2, iters, tol, min_exponent):  # pragma: no cover  (compiled)
    """(psi_K o ... o psi_1)^-1 (y) for ``y [M, D]`` (see :func:`kpflow.maps.ilwr.invert_steps`): each step undone
    in reverse order by solving g(t) = t - w(y - c - t v) = 0 on [0, 1], safeguarded Newton from the weight at
    ``y``, point by point (a point stops once its own |g| <= ``tol``)."""
    m, d = y.shape
    out = y.copy()
    floor = math.exp(min_exponent)
    for i in range(m):
        for k in range(centres.shape[0] - 1, -1, -1):
            a, b, c = 0.0, 0.0, 0.0
            for j in range(d):
                dy = out[i, j] - centres[k, j]
                a += dy * dy
                b += dy * vectors[k, j]
                c += vectors[k, j] * vectors[k, j]
            nr2 = neg_rho2[k]
            e0 = a * nr2
            t = math.exp(e0) if e0 > min_exponent else floor
            lo, hi = 0.0, 1.0
            for _ in range(iters):
                expo = nr2 * (a - 2.0 * t * b + t * t * c)
                live = expo > min_exponent
                e = math.exp(expo) if live else floor
                g = t - e
                if abs(g) <= tol:
                    break
                if g < 0:
                    lo = t
                else:
                    hi = t
                dg = 1.0 - (e * nr2 * (2.0 * t * c - 2.0 * b) if live else 0.0)
                t_new = t - g / dg
                t = t_new if lo <= t_new <= hi else 0.5 * (lo + hi)
            for j in range(d):
                out[i, j] -= t * vectors[k, j]
    return out


@numba.njit(cache=True)
def jacobian(x, a, t, centres, vectors, neg_rho2, min_exponent):  # pragma: no cover  (compiled)
    """J(x) ``[M, D, D]`` of psi_K o ... o psi_1 o (A x + t) (see :meth:`kpflow.maps.ilwr.ILWRMap._jacobian`):
    J_k = I + 2 (-rho_k^2) w_k v_k (z - c_k)^T chained through the steps, a clamped weight counting as constant."""
    m, d = x.shape
    out = np.empty((m, d, d))
    floor = math.exp(min_exponent)
    z = np.empty(d)
    row = np.empty(d)
    for i in range(m):
        jac = a.copy()
        for j in range(d):
            s = t[j]
            for q in range(d):
                s += a[j, q] * x[i, q]
            z[j] = s
        for k in range(centres.shape[0]):
            s = 0.0
            for j in range(d):
                s += (z[j] - centres[k, j]) ** 2
            w = math.exp(max(s * neg_rho2[k], min_exponent))
            if w > floor:
                for q in range(d):  # row = (z - c)^T J
                    r = 0.0
                    for j in range(d):
                        r += (z[j] - centres[k, j]) * jac[j, q]
                    row[q] = r
                scale = 2.0 * neg_rho2[k] * w
                for j in range(d):
                    for q in range(d):
                        jac[j, q] += scale * vectors[k, j] * row[q]
            for j in range(d):
                z[j] += w * vectors[k, j]
        out[i] = jac
    return out
