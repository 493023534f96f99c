"""Coherent Point Drift (Myronenko & Song 2010, via pycpd): the source points are the centroids of a Gaussian
mixture fitted by EM to the target points, with a uniform outlier component of weight ``w``. Rigid CPD moves the
centroids by a similarity transform (scale included); non-rigid CPD then lets them drift by a smooth displacement
field (Gaussian kernel of width ``beta``, regularisation ``lam``). The pose returned is the rigid one (Kabsch on
the source and its registered copy); the correspondences come from the registered points."""

from __future__ import annotations

import warnings

import numpy as np
from pycpd import DeformableRegistration, RigidRegistration

from .base import rigid_pose


def register(s: np.ndarray, y: np.ndarray, rot: np.ndarray, t: np.ndarray, w: float = 0.2, max_iters: int = 100,
             nonrigid: bool = False, beta: float = 2.0, lam: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Register source ``s [N, D]`` onto target ``y [M, D]`` from the pose ``(rot, t)``: the rigid pose and the
    registered source points ``[N, D]``."""
    # in normalised coordinates (the target's centroid at 0, the source's RMS spread 1), as Myronenko & Song do:
    # in raw pixel units the outlier weight let the scale collapse to 0
    centre, spread = y.mean(0), np.sqrt(((s - s.mean(0)) ** 2).sum(1).mean()) or 1.0
    start = (s @ rot.T + t - centre) / spread
    with warnings.catch_warnings():  # pycpd's own SyntaxWarnings and casts
        warnings.simplefilter("ignore")
        moved, _ = RigidRegistration(X=(y - centre) / spread, Y=start, w=w, max_iterations=max_iters).register()
        if nonrigid:
            moved = DeformableRegistration(
                X=(y - centre) / spread, Y=moved, w=w, beta=beta, alpha=lam, max_iterations=max_iters
            ).register()[0]
    moved = moved * spread + centre
    rot, t = rigid_pose(s, moved)
    return rot, t, moved
