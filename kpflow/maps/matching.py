"""Correspondences for unordered keypoints: multi-start rigid alignment with Hungarian assignment.

For each initial rotation R0 (a grid of angles in 2-D, of yaw x a few tilts in 3-D), alternate
(1) the assignment minimising sum_i |R s_i + t - y_pi(i)|^2 (scipy's ``linear_sum_assignment``) and
(2) the Kabsch fit of (R, t) on the assigned pairs, until the assignment stops changing (an ICP with
optimal assignment). Keep the result with the smallest residual.

Symmetric keypoint sets (a box's corners under a half turn) have several assignments with the same residual;
among those within ``tie_tol`` of the best, the one whose rotation is closest to the identity is returned, so
the answer is the true order whenever the object turned by less than half its symmetry angle, and an
equivalent order otherwise (``MatchResult.ambiguous`` says when that happened).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from kpflow.maps.affine import fit_affine
from kpflow.maps.validation import as_float_tensor, check_finite


@dataclass
class MatchResult:
    """``perm[i]`` is the index in ``target`` matched to ``source[i]`` (so ``target[perm]`` is ordered like source)."""

    perm: torch.Tensor
    rotation: torch.Tensor
    translation: torch.Tensor
    rms: float
    ambiguous: bool


def _initial_rotations(d: int, n_starts: int) -> np.ndarray:
    if d == 2:
        a = np.linspace(0, 2 * math.pi, n_starts, endpoint=False)
        return np.stack([np.stack([np.cos(a), -np.sin(a)], -1), np.stack([np.sin(a), np.cos(a)], -1)], -2)
    yaws = np.linspace(0, 2 * math.pi, n_starts, endpoint=False)
    tilts = [(0.0, 0.0), (math.pi, 0.0), (math.pi / 2, 0.0), (-math.pi / 2, 0.0), (0.0, math.pi / 2), (0.0, -math.pi / 2)]
    rots = [Rotation.from_euler("zyx", [y, p, r]).as_matrix() for r, p in tilts for y in yaws]
    return np.stack(rots)


def match_keypoints(
    source,
    target,
    n_starts: int = 12,
    max_iters: int = 20,
    tie_tol: float = 1e-3,
) -> MatchResult:
    """Find which target keypoint corresponds to each source keypoint (module docstring).

    Args:
        source, target: ``[N, D]`` (D = 2 or 3), the same N.
        n_starts: rotations tried in 2-D (yaws in 3-D, times 6 tilts).
        tie_tol: results whose RMS is within ``tie_tol`` times the keypoints' spread of the best count as ties.
    """
    src = as_float_tensor(source, "source")
    tgt = as_float_tensor(target, "target")
    if src.ndim != 2 or tgt.shape != src.shape or src.shape[-1] not in (2, 3):
        raise ValueError(f"source and target must both be [N, 2] or [N, 3]; got {tuple(src.shape)} and {tuple(tgt.shape)}")
    check_finite(src, "source")
    check_finite(tgt, "target")
    s, y = src.detach().cpu().double().numpy(), tgt.detach().cpu().double().numpy()
    n, d = s.shape
    sc = s - s.mean(0)
    spread = math.sqrt((sc**2).sum(1).mean()) or 1.0
    results = []
    for r0 in _initial_rotations(d, n_starts):
        rot, t = r0, y.mean(0) - r0 @ s.mean(0)
        perm = None
        for _ in range(max_iters):
            moved = s @ rot.T + t
            cost = ((moved[:, None, :] - y[None]) ** 2).sum(-1)
            _, new = linear_sum_assignment(cost)
            if perm is not None and np.array_equal(new, perm):
                break
            perm = new
            a, tt = fit_affine(torch.from_numpy(s)[None], torch.from_numpy(y[perm])[None], "rigid")
            rot, t = a[0].numpy(), tt[0].numpy()
        rms = math.sqrt((((s @ rot.T + t) - y[perm]) ** 2).sum(1).mean())
        results.append((rms, perm, rot, t))
    best = min(r[0] for r in results)
    ties = [r for r in results if r[0] <= best + tie_tol * spread]
    distinct = {tuple(r[1]) for r in ties}

    def angle(rot: np.ndarray) -> float:
        return float(np.arccos(np.clip((np.trace(rot) - 1) / 2 if d == 3 else rot[0, 0], -1, 1)))

    rms, perm, rot, t = min(ties, key=lambda r: angle(r[2]))
    as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=src.dtype, device=src.device)  # noqa: E731
    return MatchResult(as_t(perm).long(), as_t(rot), as_t(t), rms, ambiguous=len(distinct) > 1)
