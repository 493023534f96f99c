"""Carrying one recorded segment into the scene now: MimicGen's object-frame transform, or a keypoint map.

A segment (:class:`~kpflow.core.task.Segment`) is planned when its start is reached in the new scene, from what
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
compared with the source: ``A = (R_A, t_A)``, the rigid fit (Kabsch: :func:`~kpflow.geometry.alignment.fit_affine`) taking
the held object's keypoints in the source's hand frame to those in the hand frame now, is undone on the right of every
pose, ``R'' = R' R_A^T`` and ``x'' = x' - R'' t_A``, so the held object (not the hand) follows the source's path.
Of the orders the object's symmetry allows (a square nut's ring: four ways to sit on the peg), the one whose path
the task's ``path_cost`` rates best is taken (for the Panda: a turn within the last joint's range, ending nearest
the robot's base, as the scripted demonstrator chose; a nut grasped the other way round would otherwise be placed
by reaching past the peg). The nearest order's correction holds all along; another order's is turned into over
the segment's first phase (a place's carry, :func:`turn_ramp`), about the held object's centre
(:func:`in_hand_path`), as the scripted place turns the nut on the way: done at once, the turn fell in the transit,
with the arm still folded over the pick, where the controller took it with the fifth and sixth joints and bent
the sixth to its stop (on Square's tuning scenes, several times as often as with the turn on the way).

Either way, the arm first moves from where it is to the carried segment's first pose in
:func:`kpflow.tasks.arm.motion.interpolate`'s straight steps (MimicGen's interpolation between segments), with the
gripper as the segment begins.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from kpflow.core.task import Segment, SegmentStart
from kpflow.geometry.alignment import fit_affine
from kpflow.maps.base import TransportMap
from kpflow.tasks.arm.motion import interpolate
from kpflow.trajectory import Trajectory
from kpflow.transport import transport_trajectory


def turn_ramp(phases: np.ndarray) -> np.ndarray:
    """``s [T]``: 0 at a segment's first step rising linearly to 1 at the end of its first phase (a place's carry),
    1 after it: how far a symmetric held object has turned into its chosen order."""
    changes = np.flatnonzero(phases != phases[0])
    first = int(changes[0]) if len(changes) else len(phases)
    return np.minimum(np.arange(len(phases)) / max(first - 1, 1), 1.0)


def in_hand_path(nearest, chosen, centre: np.ndarray, ramp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The in-hand correction along a segment, ``R [T, 3, 3]`` and ``t [T, 3]``: the ``nearest`` order's fit
    ``(R_0, t_0)`` at the start turning into the ``chosen`` one's ``(R_k, t_k)`` by ``ramp``, a slerp about the held
    object's centroid ``centre`` (in the source's hand frame). Both fits take it to the same point ``c'`` (the
    centroid of the same keypoints in another order), so ``t(s) = c' - R(s) centre`` is ``t_0`` at 0 and ``t_k``
    at 1."""
    (r_0, _), (r_k, t_k) = nearest, chosen
    rots = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([r_0, r_k])))(ramp).as_matrix()
    return rots, (r_k @ centre + t_k) - rots @ centre


class SegmentTransport:
    """Plan a source segment in the scene now (module docstring). ``make_map`` None is MimicGen's object-frame
    transform; otherwise a factory of the keypoint map, fitted on the reference object's keypoints (and the grip
    site's with ``gripper_keypoint``); ``in_hand`` corrects for the held object's pose in the jaws."""

    def __init__(
        self, make_map: Callable[[], TransportMap] | None = None, gripper_keypoint: bool = False, in_hand: bool = True
    ):
        self.make_map, self.gripper_keypoint, self.in_hand = make_map, gripper_keypoint, in_hand

    def keypoints(self, start: SegmentStart) -> np.ndarray:
        """The keypoints ``[N, 3]`` the map is fitted on, from a segment's start (recorded, or observed now)."""
        return np.concatenate(list(start.keypoints.values()) + ([start.gripper] if self.gripper_keypoint else []))

    def distance(self, source: SegmentStart, now: SegmentStart) -> float:
        """How far the reference object moved between a source segment's start and ``now``, in MimicGen's
        ``nearest_neighbor_object`` measure ``|p_n - p_s| + theta`` (m + rad, its unit weights), theta the angle of
        the turn. MimicGen's family turns by the object's pose, ``R_n R_s^T``, and ``p`` is its position; a keypoint
        map's by the rigid fit of the keypoints (the least turn that looks the same, for a symmetric object), ``p``
        their centroid."""
        if self.make_map is None:
            reference = next(iter(source.keypoints))
            (p_s, r_s), (p_n, r_n) = source.poses[reference], now.poses[reference]
            turn = r_n @ r_s.T
        else:
            kp_s, kp_n = (np.concatenate(list(start.keypoints.values())) for start in (source, now))
            turn = fit_affine(*(torch.as_tensor(kp[None], dtype=torch.float64) for kp in (kp_s, kp_n)), "rigid")[0][
                0
            ].numpy()
            p_s, p_n = kp_s.mean(0), kp_n.mean(0)
        return float(np.linalg.norm(p_n - p_s) + Rotation.from_matrix(turn).magnitude())

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
                phi,
                torch.as_tensor(traj.positions, dtype=torch.float64),
                orientations=torch.as_tensor(traj.rotations, dtype=torch.float64),
            )
        return moved.positions.numpy(), moved.orientations.numpy(), moved.std.numpy()

    def carry(self, source: Segment, now: SegmentStart) -> Trajectory:
        """The source segment's trajectory moved into the scene ``now`` (without the transit to its start)."""
        positions, rotations, std = self._moved(source, now)
        if self.in_hand and source.start.in_hand is not None and now.in_hand is not None:
            held = source.start.in_hand[0]
            orders = torch.as_tensor(now.in_hand, dtype=torch.float64)  # [S, M, 3]: the held keypoints in each order
            rots, shifts = fit_affine(torch.as_tensor(held, dtype=torch.float64).expand_as(orders), orders, "rigid")
            fits = list(zip(rots.numpy(), shifts.numpy()))
            ramp = turn_ramp(source.trajectory.phases)
            candidates = []
            for k, (r_a, t_a) in enumerate(fits):
                if k == 0:  # the order nearest the source's: the same correction all along (no slerp, so bit for bit
                    # the correction without a reorder: robosuite's contacts amplify 1e-16)
                    rot = rotations @ r_a.T
                    candidates.append((positions - rot @ t_a, rot))
                    continue
                r_t, t_t = in_hand_path(fits[0], (r_a, t_a), held.mean(0), ramp)
                rot = rotations @ np.transpose(r_t, (0, 2, 1))
                candidates.append((positions - np.einsum("tij,tj->ti", rot, t_t), rot))
            if now.path_cost is not None:  # else the order nearest the source's
                candidates.sort(key=lambda c: now.path_cost(*c))
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
