"""Policy transportation of one recorded demonstration (the robosuite tasks): fit a map on the keypoints and carry
the whole end-effector trajectory through it, open loop.

With phi fitted from the source scene's keypoints S to the new scene's T (phi(S) ~= T), every commanded position
goes through phi and every orientation through the polar factor of phi's Jacobian there
(:func:`kpflow.transport.transport_trajectory`); the grasp and phases are kept as they are, and the map's standard
deviation at each position is kept as ``std``. In an identical scene phi is the identity and the demonstration is
replayed exactly.

Uncertainty that acts (``max_std``): where the map is unsure of a transported position (the norm of its standard
deviation u_t passes ``max_std``), ``on_uncertain="rigid"`` falls back towards the alignment's rigid motion A, with
weight lambda_t = clip(u_t / max_std - 1, 0, 1) (none below the threshold, all of it at twice the threshold):
x_t = (1 - lambda_t) phi(x_t) + lambda_t A(x_t), the orientation slerped by the same weight; ``"stop"`` ends the
trajectory before its first uncertain step, for a person to take over (``stopped_at`` says where).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from kpflow.maps.base import TransportMap
from kpflow.trajectory import Keypoints, Trajectory
from kpflow.transport import transport_trajectory

ON_UNCERTAIN = ("rigid", "stop")


def check_uncertainty_options(max_std: float | None, on_uncertain: str) -> None:
    """``ValueError`` naming ``max_std`` or ``on_uncertain`` when out of range."""
    if max_std is not None and not max_std > 0:
        raise ValueError(f"max_std must be > 0 or None, got {max_std}")
    if on_uncertain not in ON_UNCERTAIN:
        raise ValueError(f"on_uncertain must be one of {ON_UNCERTAIN}, got {on_uncertain!r}")


class DemoTransportPolicy:
    """``plan(demonstration, keypoints) -> (trajectory, phi)`` with a map from ``make_map`` (the policy of packing
    and stacking, beside Push-T's closed-loop :class:`~kpflow.policies.chunk_transport.TransportPolicy`);
    ``max_std`` and ``on_uncertain`` make it act on the map's uncertainty (module docstring)."""

    def __init__(self, make_map: Callable[[], TransportMap], max_std: float | None = None, on_uncertain: str = "rigid"):
        check_uncertainty_options(max_std, on_uncertain)
        self.make_map, self.max_std, self.on_uncertain = make_map, max_std, on_uncertain
        self.stopped_at: int | None = None  # the step a "stop" plan ended before (None: it runs in full)

    def plan(self, demonstration: Trajectory, keypoints: Keypoints) -> tuple[Trajectory, TransportMap]:
        kp_s = torch.as_tensor(np.asarray(keypoints.source, float))
        kp_t = torch.as_tensor(np.asarray(keypoints.target, float))
        if not torch.isfinite(kp_t).all():
            raise ValueError("the target keypoints contain NaN or inf")
        phi = self.make_map().fit(kp_s, kp_t)
        positions = torch.as_tensor(demonstration.positions, dtype=torch.float64)
        rotations = torch.as_tensor(demonstration.rotations, dtype=torch.float64)
        with torch.no_grad():
            moved = transport_trajectory(phi, positions, orientations=rotations)
        pos, rot, std = moved.positions.numpy(), moved.orientations.numpy(), moved.std.numpy()
        self.stopped_at = None
        if self.max_std is not None:
            pos, rot, std, demonstration = self._act_on_uncertainty(
                phi, demonstration, positions, rotations, pos, rot, std
            )
        return demonstration.moved(pos, rot, std), phi

    def _act_on_uncertainty(self, phi, demonstration, positions, rotations, pos, rot, std):
        u = np.linalg.norm(std, axis=1)
        if self.on_uncertain == "stop":
            over = np.flatnonzero(u > self.max_std)
            if len(over):
                n = self.stopped_at = int(over[0])
                d = demonstration
                demonstration = replace(
                    d, positions=d.positions[:n], rotations=d.rotations[:n], grasp=d.grasp[:n], phases=d.phases[:n]
                )
                pos, rot, std = pos[:n], rot[:n], std[:n]
            return pos, rot, std, demonstration
        lam = np.clip(u / self.max_std - 1.0, 0.0, 1.0)
        if lam.any() and hasattr(phi, "alignment"):
            with torch.no_grad():
                rigid = transport_trajectory(phi.alignment, positions, orientations=rotations)
            # the alignment is fitted on the map's internal batch of one keypoint set: drop that axis
            rigid_pos, rigid_rot = (
                rigid.positions.numpy().reshape(pos.shape),
                rigid.orientations.numpy().reshape(rot.shape),
            )
            pos = (1 - lam[:, None]) * pos + lam[:, None] * rigid_pos
            delta = Rotation.from_matrix(rigid_rot) * Rotation.from_matrix(rot).inv()
            rot = (Rotation.from_rotvec(delta.as_rotvec() * lam[:, None]) * Rotation.from_matrix(rot)).as_matrix()
        return pos, rot, std, demonstration
