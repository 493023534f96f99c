"""Carrying one recorded segment into the scene now: MimicGen's object-frame transform, or a keypoint map.

A segment (:class:`~kpflow.tasks.base.Segment`) is planned when its start is reached in the new scene, from what
the task observes there (:meth:`kpflow.tasks.suite.task.SuiteTask.observe`):

* ``object_frame`` (MimicGen's mechanism, the baseline): with the reference object's pose ``(R_s, p_s)`` in the
  source and ``(R_n, p_n)`` now, every commanded pose moves rigidly with it,
  ``x' = R_n R_s^T (x - p_s) + p_n`` and ``R' = R_n R_s^T R``. The reference object is the segment's first
  (the object picked; the goal of a place).
* a keypoint map phi (any :class:`~kpflow.maps.base.TransportMap`): fitted from the segment's source keypoints to
  those now (the reference object's, optionally every object of the segment's (``objects="all"``: the goal and
  the object in the hand) and the grip site's (``gripper_keypoint``)), positions go through phi and orientations
  through the polar factor of its Jacobian (:func:`kpflow.transport.transport_trajectory`).

Either way, the arm first moves from where it is to the transported segment's first pose in
:func:`kpflow.tasks.arm.motion.interpolate`'s straight steps (MimicGen's interpolation between segments), with the
gripper as the segment begins.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from kpflow.maps.base import TransportMap
from kpflow.tasks.arm.motion import interpolate
from kpflow.tasks.base import Segment, Trajectory
from kpflow.transport import transport_trajectory

OBJECTS = ("reference", "all")


class SegmentTransport:
    """Plan a source segment in the scene now (module docstring). ``make_map`` None is MimicGen's object-frame
    transform; otherwise a factory of the keypoint map, fitted on ``objects`` (``"reference"`` or ``"all"``)
    and, with ``gripper_keypoint``, the grip site."""

    def __init__(self, make_map: Callable[[], TransportMap] | None = None, objects: str = "all", gripper_keypoint: bool = True):
        if objects not in OBJECTS:
            raise ValueError(f"objects must be one of {OBJECTS}, got {objects!r}")
        self.make_map, self.objects, self.gripper_keypoint = make_map, objects, gripper_keypoint

    def keypoints(self, segment: Segment | dict) -> np.ndarray:
        """The keypoints ``[N, 3]`` the map is fitted on, from a recorded segment or an observation."""
        kp = segment.keypoints if isinstance(segment, Segment) else segment["keypoints"]
        gripper = segment.gripper if isinstance(segment, Segment) else segment["gripper"]
        names = list(kp)[:1] if self.objects == "reference" else list(kp)
        return np.concatenate([kp[n] for n in names] + ([gripper] if self.gripper_keypoint else []))

    def carry(self, source: Segment, now: dict) -> Trajectory:
        """The source segment's trajectory moved into the scene ``now`` (without the transit to its start)."""
        traj = source.trajectory
        if self.make_map is None:
            reference = next(iter(source.keypoints))
            (p_s, r_s), (p_n, r_n) = source.poses[reference], now["poses"][reference]
            turn = r_n @ r_s.T
            positions = (traj.positions - p_s) @ turn.T + p_n
            rotations = np.einsum("ij,tjk->tik", turn, traj.rotations)
            return traj.moved(positions, rotations, np.zeros_like(positions))
        kp_s = torch.as_tensor(self.keypoints(source), dtype=torch.float64)
        kp_n = torch.as_tensor(self.keypoints(now), dtype=torch.float64)
        phi = self.make_map().fit(kp_s, kp_n)
        with torch.no_grad():
            moved = transport_trajectory(
                phi, torch.as_tensor(traj.positions, dtype=torch.float64), orientations=torch.as_tensor(traj.rotations, dtype=torch.float64)
            )
        return traj.moved(moved.positions.numpy(), moved.orientations.numpy(), moved.std.numpy())

    def plan(self, source: Segment, now: dict, start_pos: np.ndarray, start_rot: np.ndarray) -> Trajectory:
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
