"""The LASA handwriting demonstrations as the map benchmarks read them (``benchmarks/shapes.py``' protocol): each
of a shape's 7 demonstrations resampled to 200 points, with a start and a goal frame at its two ends described by
five keypoints 5 mm from each origin (the units of the authors' GP settings)."""

from __future__ import annotations

import numpy as np
import torch

from kpflow.tasks.frames import end_heading, lasa_frames, load_lasa, scene_keypoints

FRAME_SIZE = 5.0  # mm: a frame's keypoints are 5 apart, the units of the authors' GP settings
N_POINTS, N_DEMOS = 200, 7


def demonstrations(shape: str) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """(positions [200, 2] mm, the ten frame keypoints [10, 2], end heading) of each demonstration of ``shape``."""
    out = []
    for k in range(N_DEMOS):
        demo = load_lasa(shape, demo=k, n=N_POINTS, scale=1.0, dtype=torch.float64)
        keypoints = scene_keypoints(list(lasa_frames(demo)), FRAME_SIZE)
        out.append((demo.positions.numpy(), keypoints.numpy(), float(end_heading(demo.positions, -1))))
    return out
