"""Straight-line motions of a cup pointing down: the orientations and the waypoints the arm can follow.

The UR5e's operational-space controller takes absolute poses; one large jump can flip its elbow and its orientation
error is blind to 180-degree rotations, so every motion is cut into steps of at most ``MAX_STEP`` and ``MAX_TURN``
(:func:`interpolate`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from kpflow.trajectory import Trajectory

MAX_STEP, MAX_TURN = 0.015, 0.1  # m and rad per control step (20 Hz): larger jumps can flip the UR5e's elbow
DOWN = Rotation.from_euler("x", np.pi).as_matrix()  # the cup pointing down
PRESS = 0.004  # m: a contact target lies this far below an object's top, so the cup touches it


def pointing_down(yaw: float) -> np.ndarray:
    """The tool (the cup, or the Panda's jaws, which then close along the world direction ``yaw``) pointing down,
    turned by ``yaw`` about the world's z axis."""
    return Rotation.from_euler("z", yaw).as_matrix() @ DOWN


def rotvec(rot: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix (the controller's orientation input)."""
    return Rotation.from_matrix(rot).as_rotvec()


def interpolate(p0, r0, p1, r1) -> tuple[np.ndarray, np.ndarray]:
    """Waypoints ``[n, 3]``, ``[n, 3, 3]`` from ``(p0, r0)`` (excluded) to ``(p1, r1)`` (included): a straight line and
    a slerp, with ``n`` the fewest steps of at most ``MAX_STEP`` and ``MAX_TURN``."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    turn = (Rotation.from_matrix(r1) * Rotation.from_matrix(r0).inv()).magnitude()
    n = max(1, int(np.ceil(max(np.linalg.norm(p1 - p0) / MAX_STEP, turn / MAX_TURN))))
    a = np.arange(1, n + 1) / n
    rots = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([r0, r1])))(a).as_matrix()
    return p0 + a[:, None] * (p1 - p0), rots


def segments_to_trajectory(start_pos, start_rot, segments: list[tuple]) -> Trajectory:
    """A trajectory from ``segments`` of ``(phase, target position, rotation, settle steps, grasp)``: each moves
    in :func:`interpolate`'s steps to its target (``"seal"`` and ``"release"`` stay where they are) and holds it for
    ``settle`` steps. Returns the :class:`~kpflow.trajectory.Trajectory`."""
    pos, rot = np.asarray(start_pos, float), np.asarray(start_rot, float)
    out = {"positions": [], "rotations": [], "grasp": [], "phases": []}
    for phase, target, target_rot, settle, grasp in segments:
        target, target_rot = np.asarray(target, float), np.asarray(target_rot, float)
        if phase in ("seal", "release"):
            ps, rs = np.empty((0, 3)), np.empty((0, 3, 3))
        else:
            ps, rs = interpolate(pos, rot, target, target_rot)
        ps = np.concatenate([ps, np.repeat(target[None], settle, 0)])
        rs = np.concatenate([rs, np.repeat(target_rot[None], settle, 0)])
        out["positions"].append(ps)
        out["rotations"].append(rs)
        out["grasp"].append(np.full(len(ps), grasp))
        out["phases"] += [phase] * len(ps)
        pos, rot = target, target_rot
    return Trajectory(**{k: (np.concatenate(v) if k != "phases" else np.array(v)) for k, v in out.items()})
