"""What every matcher shares: the result, the rigid fit of one pair (the code base's one rigid fit,
:func:`~kpflow.geometry.alignment.fit_affine`, on numpy arrays), the initial rotations of the multi-start search and the
final one-to-one assignment that leaves outliers and missing points unmatched.

A matcher (one per file: :mod:`.hungarian`, :mod:`.icp`, :mod:`.cpd`, :mod:`.ot`) refines a rigid pose of the
source onto the target from one initial rotation; :func:`~.match.match_keypoints` runs it from every start, assigns
the points one to one at each resulting pose and keeps the best.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from kpflow.geometry.alignment import fit_affine
from kpflow.geometry.angles import planar_rotation
from kpflow.maps import ilwr_kernels

#: ``perm`` entry of a source keypoint with no counterpart in the target (missing there, or too far)
UNMATCHED = -1
_F64 = torch.finfo(torch.float64)


@dataclass
class MatchResult:
    """``perm[i]`` is the index in ``target`` matched to ``source[i]``, or ``-1`` when it has none (so
    ``target[perm[perm >= 0]]`` is ordered like ``source[perm >= 0]``). ``rotation`` and ``translation`` move the
    source onto the target; ``rms`` is the residual of the matched pairs. A symmetric set has several equally
    good orders: ``alternatives`` lists each (``perm`` first, then by growing rotation from the identity) and
    ``ambiguous`` says there is more than one."""

    perm: torch.Tensor
    rotation: torch.Tensor
    translation: torch.Tensor
    rms: float
    ambiguous: bool
    alternatives: list[torch.Tensor] = field(default_factory=list)

    @property
    def matched(self) -> torch.Tensor:
        """``[N]`` bool: the source keypoints that have a counterpart."""
        return self.perm >= 0


def rigid_pose(s: np.ndarray, y: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The proper rotation R and translation t minimising sum_i w_i |R s_i + t - y_i|^2 for one pair ``[N, D]``:
    ``fit_affine(s, y, "rigid", weights)`` (weighted Kabsch, reflection-safe), in and out as float64 numpy. Without
    weights its compiled form :func:`~kpflow.maps.ilwr_kernels.align` computes it where that does not decline (a
    matcher fits hundreds of small pairs)."""
    s, y = np.ascontiguousarray(s, np.float64), np.ascontiguousarray(y, np.float64)
    if weights is None:
        rot, t, ok = ilwr_kernels.align(s, y, ilwr_kernels.ALIGN_KINDS["rigid"], _F64.eps, _F64.tiny)
        if ok:
            return rot, t
    w = None if weights is None else torch.as_tensor(np.asarray(weights, np.float64))
    rot, t = fit_affine(torch.from_numpy(s)[None], torch.from_numpy(y)[None], "rigid", w)
    return rot[0].numpy(), t[0].numpy()


def initial_rotations(d: int, n_starts: int) -> np.ndarray:
    """``n_starts`` rotations about the origin in 2-D; in 3-D ``n_starts`` yaws times six tilts (z up, down, and
    the four sides)."""
    if d == 2:
        return planar_rotation(np.linspace(0, 2 * math.pi, n_starts, endpoint=False))
    yaws = np.linspace(0, 2 * math.pi, n_starts, endpoint=False)
    tilts = [
        (0.0, 0.0),
        (math.pi, 0.0),
        (math.pi / 2, 0.0),
        (-math.pi / 2, 0.0),
        (0.0, math.pi / 2),
        (0.0, -math.pi / 2),
    ]
    return np.stack([Rotation.from_euler("zyx", [y, p, r]).as_matrix() for r, p in tilts for y in yaws])


def assign(
    s: np.ndarray, y: np.ndarray, rot: np.ndarray, t: np.ndarray, max_distance: float | None
) -> tuple[np.ndarray, float, float]:
    """One-to-one assignment of the moved source to the target (``linear_sum_assignment``): ``perm [N]`` (-1:
    unmatched), the score (mean over the source of the squared distance, truncated at ``max_distance^2`` where a
    point stays unmatched; without ``max_distance``, over the matched pairs) and the matched pairs' RMS."""
    cost = (((s @ rot.T + t)[:, None, :] - y[None]) ** 2).sum(-1)
    n, m = cost.shape
    if max_distance is not None:
        cost = np.concatenate([cost, np.full((n, n), max_distance**2)], 1)  # a dummy target per source point
    rows, cols = linear_sum_assignment(cost)
    perm = np.full(n, UNMATCHED)
    real = cols < m
    perm[rows[real]] = cols[real]
    paired = cost[rows[real], cols[real]]
    rms = math.sqrt(paired.mean()) if len(paired) else math.inf
    score = cost[rows, cols].sum() / n if max_distance is not None else (paired.mean() if len(paired) else math.inf)
    return perm, float(score), rms


def rotation_angle(rot: np.ndarray) -> float:
    """The angle of a 2-D or 3-D rotation (rad)."""
    c = rot[0, 0] if rot.shape[0] == 2 else (np.trace(rot) - 1) / 2
    return float(np.arccos(np.clip(c, -1, 1)))
