"""Iterative closest point (Besl & McKay 1992): alternate (1) each source point's nearest target point (scipy's
``cKDTree``; several may share one) and (2) the Kabsch fit of (R, t) on those pairs, until the pose stops moving.
Pairs farther than ``max(max_distance, 2.5 x the median pair distance)`` are left out of the fit (after Zhang
1994's statistical rejection: loose while the pose is far off, down to ``max_distance`` once it has converged),
which keeps outliers and missing points from pulling the pose."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .base import rigid_pose


def register(s: np.ndarray, y: np.ndarray, rot: np.ndarray, t: np.ndarray, max_iters: int = 30, max_distance: float | None = None,
             tol: float = 1e-10) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Refine the rigid pose ``(rot, t)`` of source ``s [N, D]`` onto target ``y [M, D]``."""
    tree = cKDTree(y)
    for _ in range(max_iters):
        dist, nearest = tree.query(s @ rot.T + t)
        keep = dist <= max(max_distance, 2.5 * np.median(dist)) if max_distance is not None else np.ones(len(s), bool)
        if keep.sum() < s.shape[1]:
            break  # too few pairs to fix a pose: keep the last one
        new_rot, new_t = rigid_pose(s[keep], y[nearest[keep]])
        moved = np.abs(new_rot - rot).max() + np.abs(new_t - t).max()
        rot, t = new_rot, new_t
        if moved < tol:
            break
    return rot, t
