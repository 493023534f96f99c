"""Registration by optimal assignment: alternate (1) the assignment minimising sum_i |R s_i + t - y_pi(i)|^2
(scipy's ``linear_sum_assignment``; rectangular when the sets differ in size) and (2) the Kabsch fit of (R, t) on
the assigned pairs, until the assignment stops changing (an ICP whose correspondences are one to one)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from .base import rigid_pose


def register(
    s: np.ndarray, y: np.ndarray, rot: np.ndarray, t: np.ndarray, max_iters: int = 20
) -> tuple[np.ndarray, np.ndarray]:
    """Refine the rigid pose ``(rot, t)`` of source ``s [N, D]`` onto target ``y [M, D]``."""
    pairs = None
    for _ in range(max_iters):
        cost = (((s @ rot.T + t)[:, None, :] - y[None]) ** 2).sum(-1)
        rows, cols = linear_sum_assignment(cost)
        if pairs is not None and np.array_equal(cols, pairs[1]) and np.array_equal(rows, pairs[0]):
            break
        pairs = (rows, cols)
        rot, t = rigid_pose(s[rows], y[cols])
    return rot, t
