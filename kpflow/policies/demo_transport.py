"""Policy transportation of one recorded demonstration (the robosuite tasks): fit a map on the keypoints and carry
the whole end-effector trajectory through it, open loop.

With phi fitted from the source scene's keypoints S to the new scene's T (phi(S) ~= T), every commanded position
goes through phi and every orientation through the polar factor of phi's Jacobian there
(:func:`kpflow.transport.transport_trajectory`); suction and phases are kept as they are, and the map's standard
deviation at each position is kept as ``std``. In an identical scene phi is the identity and the demonstration is
replayed exactly.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from kpflow.maps.base import TransportMap
from kpflow.tasks.base import Keypoints, Trajectory
from kpflow.transport import transport_trajectory


class DemoTransportPolicy:
    """``plan(demonstration, keypoints) -> (trajectory, phi)`` with a map from ``make_map`` (the policy of packing
    and stacking, beside Push-T's closed-loop :class:`~kpflow.policies.chunk_transport.TransportPolicy`)."""

    def __init__(self, make_map: Callable[[], TransportMap]):
        self.make_map = make_map

    def plan(self, demonstration: Trajectory, keypoints: Keypoints) -> tuple[Trajectory, TransportMap]:
        kp_s = torch.as_tensor(np.asarray(keypoints.source, float))
        kp_t = torch.as_tensor(np.asarray(keypoints.target, float))
        if not torch.isfinite(kp_t).all():
            raise ValueError("the target keypoints contain NaN or inf")
        phi = self.make_map().fit(kp_s, kp_t)
        with torch.no_grad():
            moved = transport_trajectory(
                phi,
                torch.as_tensor(demonstration.positions, dtype=torch.float64),
                orientations=torch.as_tensor(demonstration.rotations, dtype=torch.float64),
            )
        return demonstration.moved(moved.positions.numpy(), moved.orientations.numpy(), moved.std.numpy()), phi
