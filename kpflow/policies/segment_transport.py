"""Carrying one recorded segment into the scene now: MimicGen's object-frame transform, or a keypoint map.

A segment (:class:`~kpflow.tasks.base.Segment`) is planned when its start is reached in the new scene, from what
the task observes there (:meth:`kpflow.tasks.suite.task.SuiteTask.observe`): the reference object's pose and
keypoints (the object picked, or the goal of a place), the grip site, and the held object's keypoints in the hand.

* ``make_map=None``: MimicGen's mechanism, the baseline. With the reference object's pose ``(R_s, p_s)`` in the
  source and ``(R_n, p_n)`` now, every commanded pose moves rigidly with it, ``x' = R_n R_s^T (x - p_s) + p_n``
  and ``R' = R_n R_s^T R``.
* a keypoint map phi (any :class:`~kpflow.maps.base.TransportMap`), fitted from the reference object's source
  keypoints to those now (and the grip site's, with ``gripper_keypoint``): positions go through phi, orientations
  through the polar factor of its Jacobian (:func:`kpflow.transport.transport_trajectory`). Symmetric keypoints
  (:mod:`kpflow.tasks.suite.keypoints`) make phi turn by the least rotation that looks the same.

With ``in_hand`` (and a held object), the carried poses are corrected for how the object sits in the jaws now
compared with the source: ``A = (R_A, t_A)``, the rigid fit (Kabsch, scipy's ``Rotation.align_vectors``) taking the
held object's keypoints in the source's hand frame to those in the hand frame now, is undone on the right of every
pose, ``R'' = R' R_A^T`` and ``x'' = x' - R'' t_A``, so the held object (not the hand) follows the source's path.
Of the orders the object's symmetry allows (a square nut's ring: four ways to sit on the peg), the one whose end
pose the task's ``end_pose_cost`` rates best is taken (for the Panda: within the last joint's range, nearest the
robot's base, as the scripted demonstrator chose; a nut grasped the other way round would otherwise be placed by
reaching past the peg).

Either way, the arm first moves from where it is to the carried segment's first pose in
:func:`kpflow.tasks.arm.motion.interpolate`'s straight steps (MimicGen's interpolation between segments), with the
gripper as the segment begins.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from kpflow.maps.base import TransportMap
from kpflow.tasks.arm.motion import interpolate
from kpflow.tasks.base import Segment, SegmentStart, Trajectory
from kpflow.transport import transport_trajectory


def rigid_fit(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` minimising ``sum |R s_i + t - t_i|^2`` over corresponding points ``[N, 3]`` (Kabsch)."""
    ms, mt = source.mean(0), target.mean(0)
    rot, _ = Rotation.align_vectors(target - mt, source - ms)
    r = rot.as_matrix()
    return r, mt - r @ ms


class SegmentTransport:
    """Plan a source segment in the scene now (module docstring). ``make_map`` None is MimicGen's object-frame
    transform; otherwise a factory of the keypoint map, fitted on the reference object's keypoints (and the grip
    site's with ``gripper_keypoint``); ``in_hand`` corrects for the held object's pose in the jaws."""

    def __init__(self, make_map: Callable[[], TransportMap] | None = None, gripper_keypoint: bool = False, in_hand: bool = True):
        self.make_map, self.gripper_keypoint, self.in_hand = make_map, gripper_keypoint, in_hand

    def keypoints(self, start: SegmentStart) -> np.ndarray:
        """The keypoints ``[N, 3]`` the map is fitted on, from a segment's start (recorded, or observed now)."""
        return np.concatenate(list(start.keypoints.values()) + ([start.gripper] if self.gripper_keypoint else []))

    def _moved(self, source: Segment, now: SegmentStart) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        traj = source.trajectory
        if self.make_map is None:
            reference = next(iter(source.start.keypoints))
            (p_s, r_s), (p_n, r_n) = source.start.poses[reference], now.poses[reference]
            turn = r_n @ r_s.T
            positions = (traj.positions - p_s) @ turn.T + p_n
            return positions, np.einsum("ij,tjk->tik", turn, traj.rotations), np.zeros_like(positions)
        kp_s = torch.as_tensor(self.keypoints(source.start), dtype=torch.float64)
        kp_n = torch.as_tensor(self.keypoints(now), dtype=torch.float64)
        phi = self.make_map().fit(kp_s, kp_n)
        with torch.no_grad():
            moved = transport_trajectory(
                phi, torch.as_tensor(traj.positions, dtype=torch.float64), orientations=torch.as_tensor(traj.rotations, dtype=torch.float64)
            )
        return moved.positions.numpy(), moved.orientations.numpy(), moved.std.numpy()

    def carry(self, source: Segment, now: SegmentStart) -> Trajectory:
        """The source segment's trajectory moved into the scene ``now`` (without the transit to its start)."""
        positions, rotations, std = self._moved(source, now)
        if self.in_hand and source.start.in_hand is not None and now.in_hand is not None:
            held = source.start.in_hand[0]
            candidates = []
            for keypoints in now.in_hand:
                r_a, t_a = rigid_fit(held, keypoints)
                rot = rotations @ r_a.T
                candidates.append((positions - rot @ t_a, rot))
            if now.end_pose_cost is not None:  # else the order nearest the source's
                candidates.sort(key=lambda c: now.end_pose_cost(c[0][-1], c[1][-1]))
            positions, rotations = candidates[0]
        return source.trajectory.moved(positions, rotations, std)

    def plan(self, source: Segment, now: SegmentStart, start_pos: np.ndarray, start_rot: np.ndarray) -> Trajectory:
        """The transit from ``(start_pos, start_rot)`` to the carried segment, then the segment."""
        carried = self.carry(source, now)
        ps, rs = interpolate(start_pos, start_rot, carried.positions[0], carried.rotations[0])
        n = len(ps)
        return Trajectory(
            positions=np.concatenate([ps, carried.positions]),
            rotations=np.concatenate([rs, carried.rotations]),
            grasp=np.concatenate([np.full(n, carried.grasp[0]), carried.grasp]),
            phases=np.concatenate([np.full(n, "transit"), carried.phases]),
            std=np.concatenate([np.zeros((n, 3)), carried.std]),
        )
