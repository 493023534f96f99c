"""Coherent Point Drift (Myronenko & Song 2010, via pycpd): the source points are the centroids of a Gaussian
mixture fitted by EM to the target points, with a uniform outlier component of weight ``w``. Rigid CPD moves the
centroids by a similarity transform (scale included); non-rigid CPD then lets them drift by a smooth displacement
field (Gaussian kernel of width ``beta``, regularisation ``lam``). The pose returned is the rigid one (Kabsch on
the source and its registered copy); the correspondences come from the registered points."""

from __future__ import annotations

import warnings

import numpy as np
from pycpd import DeformableRegistration, RigidRegistration

from .base import kabsch


def register(s: np.ndarray, y: np.ndarray, rot: np.ndarray, t: np.ndarray, w: float = 0.2, max_iters: int = 100,
             nonrigid: bool = False, beta: float = 2.0, lam: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Register source ``s [N, D]`` onto target ``y [M, D]`` from the pose ``(rot, t)``: the rigid pose and the
    registered source points ``[N, D]``."""
    start = s @ rot.T + t
    with warnings.catch_warnings():  # pycpd's own SyntaxWarnings and casts
        warnings.simplefilter("ignore")
        rigid = RigidRegistration(X=y, Y=start, w=w, max_iterations=max_iters)
        moved, _ = rigid.register()
        if nonrigid:
            spread = np.sqrt(((s - s.mean(0)) ** 2).sum(1).mean()) or 1.0
            deform = DeformableRegistration(X=y / spread, Y=moved / spread, w=w, beta=beta, alpha=lam, max_iterations=max_iters)
            moved = deform.register()[0] * spread
    rot, t = kabsch(s, moved)
    return rot, t, moved
