"""Registration by entropic optimal transport (Cuturi 2013, POT): alternate (1) the transport plan between the moved
source and the target that minimises <P, C> - eps H(P) for the squared distances C (Sinkhorn; unbalanced, with
marginal relaxation ``reg_m``, when points may be missing or extra: Chizat et al. 2018) and (2) the Kabsch fit of
(R, t) of each source point onto its plan-weighted target mean, weighted by the mass it sends."""

from __future__ import annotations

import warnings

import numpy as np
import ot

from .base import rigid_pose


def register(s: np.ndarray, y: np.ndarray, rot: np.ndarray, t: np.ndarray, eps: float = 0.02, reg_m: float | None = None,
             max_iters: int = 10, tol: float = 1e-8) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Refine the rigid pose ``(rot, t)`` of source ``s [N, D]`` onto target ``y [M, D]``; ``eps`` and ``reg_m``
    are relative to the mean squared distance over all pairs at the current pose (so they do not depend on the
    units, and the plan sharpens as the pose converges)."""
    a, b = np.full(len(s), 1.0 / len(s)), np.full(len(y), 1.0 / len(y))
    with warnings.catch_warnings():  # a Sinkhorn stopped at numItermax still gives a usable plan
        warnings.filterwarnings("ignore", message="Sinkhorn did not converge")
        return _alternate(s, y, rot, t, a, b, eps, reg_m, max_iters, tol)


def _alternate(s, y, rot, t, a, b, eps, reg_m, max_iters, tol):
    for _ in range(max_iters):
        cost = (((s @ rot.T + t)[:, None, :] - y[None]) ** 2).sum(-1)
        cost = np.minimum(cost / (cost.mean() + 1e-300), 10.0)  # exp(-10 / eps) stays a normal float
        if reg_m is None:
            plan = ot.sinkhorn(a, b, cost, eps, numItermax=100, stopThr=1e-7)
        else:
            plan = ot.unbalanced.sinkhorn_unbalanced(a, b, cost, eps, reg_m, numItermax=100, stopThr=1e-7)
        mass = plan.sum(1)
        keep = mass > 1e-12
        if keep.sum() < s.shape[1]:
            break
        targets = plan[keep] @ y / mass[keep, None]
        new_rot, new_t = rigid_pose(s[keep], targets, mass[keep])
        moved = np.abs(new_rot - rot).max() + np.abs(new_t - t).max()
        rot, t = new_rot, new_t
        if moved < tol:
            break
    return rot, t
