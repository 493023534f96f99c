"""Carrying a recorded end-effector trajectory into a new scene through a map fitted on keypoints.

Positions go through ``phi`` and orientations through the polar factor of its Jacobian
(:func:`kpflow.transport.transport_trajectory`); suction and phase labels are kept as they are.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from kpflow.maps.base import TransportMap
from kpflow.transport import transport_trajectory


def transport_demo(
    trajectory: dict, source_keypoints: np.ndarray, target_keypoints: np.ndarray, make_map: Callable[[], TransportMap]
) -> dict:
    """``trajectory`` (positions, rotations, suction, phases) carried by a map fitted from ``source_keypoints
    [N, 3]`` to ``target_keypoints [N, 3]``: a trajectory plus ``std [T, 3]`` (the map's uncertainty) and the fitted
    ``map``."""
    kp_s = torch.as_tensor(np.asarray(source_keypoints, float))
    kp_t = torch.as_tensor(np.asarray(target_keypoints, float))
    if kp_t.shape != kp_s.shape or not torch.isfinite(kp_t).all():
        raise ValueError(f"target keypoints must be finite with shape {tuple(kp_s.shape)}; got {tuple(kp_t.shape)}")
    phi = make_map().fit(kp_s, kp_t)
    with torch.no_grad():
        moved = transport_trajectory(
            phi,
            torch.as_tensor(trajectory["positions"], dtype=torch.float64),
            orientations=torch.as_tensor(trajectory["rotations"], dtype=torch.float64),
        )
    return {
        "positions": moved.positions.numpy(),
        "rotations": moved.orientations.numpy(),
        "suction": trajectory["suction"].copy(),
        "phases": trajectory["phases"].copy(),
        "std": moved.std.numpy(),
        "map": phi,
    }
