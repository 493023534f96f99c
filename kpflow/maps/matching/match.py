"""Correspondences for unordered keypoints, found by a multi-start registration (one matcher per file).

For each initial rotation R0 (a grid of angles in 2-D, of yaw x six tilts in 3-D; the translation aligns the
centroids) the chosen matcher refines the rigid pose of the source onto the target: ``hungarian`` (optimal
one-to-one assignment and Kabsch, alternated), ``icp`` (nearest neighbours and Kabsch), ``cpd`` / ``cpd_nonrigid``
(Coherent Point Drift, pycpd) or ``ot`` (entropic optimal transport, POT). At each resulting pose the points are
assigned one to one (:func:`~.base.assign`); with ``max_distance`` a source point farther than that from every free
target point stays unmatched (an outlier in the target, or a keypoint the target misses), and the sets may differ
in size. The pose with the best score wins.

Symmetric keypoint sets (a box's corners under a half turn) have several assignments with the same score; every
distinct one within ``tie_tol`` of the best is returned in ``alternatives``, the one whose rotation is closest to
the identity first (the true order whenever the object turned by less than half its symmetry angle), and
``ambiguous`` is set.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from kpflow.maps.validation import as_float_tensor, check_finite

from . import cpd, hungarian, icp, ot
from .base import MatchResult, assign, initial_rotations, rotation_angle

METHODS = ("hungarian", "icp", "cpd", "cpd_nonrigid", "ot")


def _register(method: str, s, y, rot, t, max_iters: int, max_distance: float | None, options: dict):
    if method == "hungarian":
        return hungarian.register(s, y, rot, t, max_iters=max_iters)
    if method == "icp":
        return icp.register(s, y, rot, t, max_iters=max_iters, max_distance=max_distance, **options)
    if method in ("cpd", "cpd_nonrigid"):
        return cpd.register(s, y, rot, t, nonrigid=method == "cpd_nonrigid", **options)[:2]
    return ot.register(s, y, rot, t, **options)  # its own (fewer) outer iterations: each runs a Sinkhorn


def match_keypoints(
    source,
    target,
    method: str = "hungarian",
    n_starts: int = 12,
    max_iters: int = 20,
    tie_tol: float = 1e-3,
    max_distance: float | None = None,
    **options,
) -> MatchResult:
    """Find which target keypoint corresponds to each source keypoint (module docstring).

    Args:
        source, target: ``[N, D]`` and ``[M, D]`` (D = 2 or 3); M may differ from N.
        method: one of :data:`METHODS`.
        n_starts: rotations tried in 2-D (yaws in 3-D, times 6 tilts).
        tie_tol: results whose RMS is within ``tie_tol`` times the keypoints' spread of the best count as ties.
        max_distance: pairs farther apart stay unmatched (in the keypoints' units; None: every point is matched
            while the smaller set lasts).
        options: the matcher's own settings (``cpd``: ``w``, ``beta``, ``lam``; ``ot``: ``eps``, ``reg_m``).
    """
    if method not in METHODS:
        raise ValueError(f"unknown matching method {method!r}; choose one of {METHODS}")
    src = as_float_tensor(source, "source")
    tgt = as_float_tensor(target, "target")
    if src.ndim != 2 or tgt.ndim != 2 or src.shape[-1] != tgt.shape[-1] or src.shape[-1] not in (2, 3):
        raise ValueError(
            f"source and target must be [N, 2] and [M, 2] (or [.., 3]); got {tuple(src.shape)} and {tuple(tgt.shape)}"
        )
    if min(len(src), len(tgt)) < src.shape[-1] + 1:
        raise ValueError(
            f"matching needs at least {src.shape[-1] + 1} points in each set; got {len(src)} and {len(tgt)}"
        )
    if max_distance is not None and not max_distance > 0:
        raise ValueError(f"max_distance must be > 0 or None, got {max_distance}")
    check_finite(src, "source")
    check_finite(tgt, "target")
    s, y = src.detach().cpu().double().numpy(), tgt.detach().cpu().double().numpy()
    spread = math.sqrt(((s - s.mean(0)) ** 2).sum(1).mean()) or 1.0
    results = []
    for r0 in initial_rotations(s.shape[1], n_starts):
        rot, t = _register(method, s, y, r0, y.mean(0) - r0 @ s.mean(0), max_iters, max_distance, options)
        perm, score, rms = assign(s, y, rot, t, max_distance)
        results.append((math.sqrt(score), perm, rot, t, rms))
    best = min(r[0] for r in results)
    ties = sorted((r for r in results if r[0] <= best + tie_tol * spread), key=lambda r: rotation_angle(r[2]))
    distinct = list({tuple(r[1]): r for r in ties}.values())
    _, perm, rot, t, rms = distinct[0]
    as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=src.dtype, device=src.device)  # noqa: E731
    alternatives = [as_t(r[1]).long() for r in distinct]
    return MatchResult(alternatives[0], as_t(rot), as_t(t), rms, ambiguous=len(distinct) > 1, alternatives=alternatives)
