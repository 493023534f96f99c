"""The conditional flow's layers as fused loops (numba): the CPU float64 fast path of
:class:`~kpflow.maps.learned.LearnedMap`.

They compute what :meth:`ConditionalFlow.condition` (from the encoder's outputs on) and
:meth:`ConditionalFlow.forward` / :meth:`ConditionalFlow.inverse` compute, layer by layer and point by point, in
float64: a 16-layer flow is some 20 tensor operations per layer, so per-operation overhead made a scene tens of
milliseconds while its arithmetic is a fraction of one. Results agree with the torch path to rounding
(``tests/test_learned_map.py``). Compiled on first use and cached beside the module.

Weights are passed as arrays ``[K, ...]`` (one slice per layer; :func:`pack` builds them from a flow) and the scene's
condition as ``[B, K, ...]`` arrays.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch


def pack(flow) -> tuple[np.ndarray, ...]:
    """``(rotations, w1, b1, w2, b2, w3, b3)`` of a :class:`~kpflow.maps.conditional_flow.ConditionalFlow`, float64
    (``w2, b2`` empty, ``[K, 0, 0]`` and ``[K, 0]``, for a coupling depth of 1)."""
    as_np = lambda ts: np.ascontiguousarray(torch.stack(list(ts)).detach().to("cpu", torch.float64).numpy())  # noqa: E731
    k = flow.n_layers
    w2, b2 = (
        (as_np(m.weight for m in flow.w2), as_np(m.bias for m in flow.w2))
        if len(flow.w2)
        else (np.zeros((k, 0, 0)), np.zeros((k, 0)))
    )
    return (
        np.ascontiguousarray(flow.rotations.detach().to("cpu", torch.float64).numpy()),
        as_np(m.weight for m in flow.w1),
        as_np(m.bias for m in flow.w1),
        w2,
        b2,
        as_np(m.weight for m in flow.w3),
        as_np(m.bias for m in flow.w3),
    )


@numba.njit(cache=True)
def _shift_scale(k, keep, w1, b1, w2, b2, w3, b3, pc, gate, width, pts, vals, s_max, s, t, h1, h2):  # pragma: no cover
    """Layer k's log-scale ``s`` and shift ``t`` (each ``[n_move]``, written in place) at kept coordinates ``keep``."""
    hidden, n_keep, n_move = w1.shape[1], w1.shape[2], s.shape[0]
    for i in range(hidden):
        acc = b1[k, i] + pc[k, i]
        for j in range(n_keep):
            acc += w1[k, i, j] * keep[j]
        h1[i] = math.tanh(acc)
    if w2.shape[1] == 0:  # one hidden layer
        h2[:] = h1
    for i in range(w2.shape[1]):
        acc = b2[k, i]
        for j in range(hidden):
            acc += w2[k, i, j] * h1[j]
        h2[i] = math.tanh(acc)
    for o in range(n_move):
        acc_s, acc_t = b3[k, o], b3[k, n_move + o]
        for j in range(hidden):
            acc_s += w3[k, o, j] * h2[j]
            acc_t += w3[k, n_move + o, j] * h2[j]
        s[o] = gate[k] * s_max * math.tanh(acc_s / s_max)
        t[o] = gate[k] * acc_t
    inv = 1.0 / (2.0 * width[k] * width[k])
    for n in range(pts.shape[1]):
        d2 = 0.0
        for j in range(n_keep):
            e = keep[j] - pts[k, n, j]
            d2 += e * e
        kv = math.exp(-d2 * inv)
        for o in range(n_move):
            t[o] += kv * vals[k, n, o]


@numba.njit(cache=True)
def _layer(
    k, u, inverse, rot, w1, b1, w2, b2, w3, b3, pc, gate, width, pts, vals, s_max, v, s, t, h1, h2
):  # pragma: no cover
    """Layer k (or its inverse) applied in place to each row of ``u [M, D]``; returns the summed log-scales."""
    d, n_keep = u.shape[1], w1.shape[2]
    total = 0.0
    for m in range(u.shape[0]):
        for j in range(d):
            acc = 0.0
            for i in range(d):
                acc += rot[k, j, i] * u[m, i]
            v[j] = acc
        _shift_scale(k, v[:n_keep], w1, b1, w2, b2, w3, b3, pc, gate, width, pts, vals, s_max, s, t, h1, h2)
        for o in range(s.shape[0]):
            if inverse:
                v[n_keep + o] = (v[n_keep + o] - t[o]) * math.exp(-s[o])
            else:
                v[n_keep + o] = v[n_keep + o] * math.exp(s[o]) + t[o]
            total += s[o]
        for i in range(d):
            acc = 0.0
            for j in range(d):
                acc += v[j] * rot[k, j, i]
            u[m, i] = acc
    return total


@numba.njit(cache=True)
def _rotated_pair(k, p, b, rot, n_keep, rv, rhs):  # pragma: no cover  (compiled)
    """Keypoints ``p`` rotated by layer k into ``rv [N, D]``, and the moved coordinates of ``b - p`` into ``rhs``."""
    n, d = p.shape
    for i in range(n):
        for j in range(d):
            acc_p, acc_b = 0.0, 0.0
            for m in range(d):
                acc_p += rot[k, j, m] * p[i, m]
                acc_b += rot[k, j, m] * b[i, m]
            rv[i, j] = acc_p
            if j >= n_keep:
                rhs[i, j - n_keep] = acc_b - acc_p


@numba.njit(cache=True)
def _gram(rv, n_keep, width, ridge, gram):  # pragma: no cover  (compiled)
    """K + ridge I over the kept coordinates of ``rv`` into ``gram [N, N]``."""
    n = rv.shape[0]
    inv = 1.0 / (2.0 * width * width)
    for i in range(n):
        for i2 in range(n):
            d2 = 0.0
            for j in range(n_keep):
                e = rv[i, j] - rv[i2, j]
                d2 += e * e
            gram[i, i2] = math.exp(-d2 * inv)
        gram[i, i] += ridge


@numba.njit(cache=True)
def condition_layers(a, b, rot, w1, b1, w2, b2, w3, b3, pc, gate, width, step, ridge, s_max):  # pragma: no cover
    """Per scene and layer, the keypoints' kept coordinates ``pts [B, K, N, n_keep]`` and the kernel term's values
    ``vals [B, K, N, n_move]`` (``ConditionalFlow.condition``), given the encoder's outputs ``pc [B, K, H]`` and
    ``gate, width, step, ridge [B, K]``."""
    nb, n, d = a.shape
    n_layers, hidden, n_keep = w1.shape[0], w1.shape[1], w1.shape[2]
    n_move = d - n_keep
    pts = np.zeros((nb, n_layers, n, n_keep))
    vals = np.zeros((nb, n_layers, n, n_move))
    v, s, t = np.empty(d), np.empty(n_move), np.empty(n_move)
    h1, h2 = np.empty(hidden), np.empty(hidden)
    gram, rhs = np.empty((n, n)), np.empty((n, n_move))
    rv = np.empty((n, d))
    for bi in range(nb):
        p = a[bi].copy()
        for k in range(n_layers):
            _rotated_pair(k, p, b[bi], rot, n_keep, rv, rhs)
            pts[bi, k] = rv[:, :n_keep]
            _gram(rv, n_keep, width[bi, k], ridge[bi, k], gram)
            sol = np.linalg.solve(gram, rhs)
            for i in range(n):
                for o in range(n_move):
                    vals[bi, k, i, o] = step[bi, k] * sol[i, o]
            _layer(
                k,
                p,
                False,
                rot,
                w1,
                b1,
                w2,
                b2,
                w3,
                b3,
                pc[bi],
                gate[bi],
                width[bi],
                pts[bi],
                vals[bi],
                s_max,
                v,
                s,
                t,
                h1,
                h2,
            )
    return pts, vals


@numba.njit(cache=True)
def transport(u, inverse, rot, w1, b1, w2, b2, w3, b3, pc, gate, width, pts, vals, s_max):  # pragma: no cover
    """G(u) (or G^-1(u)) for points ``u [B, M, D]`` and the log-determinant ``[B, M]`` (forward only; zeros when
    ``inverse``)."""
    nb, m, d = u.shape
    n_layers, hidden, n_keep = w1.shape[0], w1.shape[1], w1.shape[2]
    n_move = d - n_keep
    out = u.copy()
    logdet = np.zeros((nb, m))
    v, s, t = np.empty(d), np.empty(n_move), np.empty(n_move)
    h1, h2 = np.empty(hidden), np.empty(hidden)
    for bi in range(nb):
        for mi in range(m):
            row = out[bi, mi : mi + 1]
            for kk in range(n_layers):
                k = n_layers - 1 - kk if inverse else kk
                ld = _layer(
                    k,
                    row,
                    inverse,
                    rot,
                    w1,
                    b1,
                    w2,
                    b2,
                    w3,
                    b3,
                    pc[bi],
                    gate[bi],
                    width[bi],
                    pts[bi],
                    vals[bi],
                    s_max,
                    v,
                    s,
                    t,
                    h1,
                    h2,
                )
                if not inverse:
                    logdet[bi, mi] += ld
    return out, logdet
