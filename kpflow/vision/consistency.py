"""Rejecting correspondences that break rigidity, after lifting them to 3-D.

A rigid motion keeps distances: two pairs on one rigid object satisfy | |s_i - s_j| - |t_i - t_j| | = 0. A pair
whose source point has neighbours (source points within ``radius``) but keeps its distance (within ``tolerance``)
to none of them is inconsistent with every object around it, and is dropped; a pair without neighbours is kept,
since nothing can vouch for or against it. One wrong pair among a handful bends a map fitted through all of them
(a GP interpolates it), so dropping it matters more than keeping every right one.

The vote is one pass and symmetric, so it cannot tell which of two lone neighbours is wrong: both are dropped. Two
wrong pairs that happen to keep their distance to each other keep each other.
"""

from __future__ import annotations

import numpy as np


def rigidly_consistent(
    source: np.ndarray, target: np.ndarray, radius: float = 0.12, tolerance: float = 0.015
) -> np.ndarray:
    """Mask ``[n]`` of the pairs ``source [n, 3]`` -> ``target [n, 3]`` to keep (module docstring)."""
    source, target = np.asarray(source, float), np.asarray(target, float)
    if source.shape != target.shape or source.ndim != 2:
        raise ValueError(f"source and target must both be [n, D]; got {source.shape} and {target.shape}")
    if radius <= 0 or tolerance <= 0:
        raise ValueError(f"radius and tolerance must be > 0, got {radius} and {tolerance}")
    d_source = np.linalg.norm(source[:, None] - source[None], axis=-1)
    d_target = np.linalg.norm(target[:, None] - target[None], axis=-1)
    others = ~np.eye(len(source), dtype=bool)
    neighbours = (d_source < radius) & others
    consistent = neighbours & (np.abs(d_source - d_target) < tolerance)
    return ~neighbours.any(axis=1) | consistent.any(axis=1)
