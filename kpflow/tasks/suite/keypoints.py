"""Keypoints of the benchmark tasks' objects, from the simulator's object pose and geometry.

A keypoint set names what a grasp or a placement depends on, and keeps the object's symmetries: a cube's eight
corners look the same after a quarter turn, so they are ordered by the cube's axis nearest a reference yaw (the
source scene's), not by its body frame; the transport then turns the gripper by at most 45 degrees, where an
object-frame transform turns it by the cube's full yaw. Per kind (``[N, 3]``, world frame, m):

* ``cube`` (lift, stack): the 8 corners of the box; symmetric under quarter turns about the vertical.
* ``can``: the centres of its top and bottom and 4 points on the rim in fixed world directions: a cylinder has no
  yaw to see, so none is transported.
* ``nut`` (square): the ring's centre, its 4 outer corners and the handle's two ends: the handle fixes the yaw.
* ``nut_handle``: the 4 corners of the handle's top face and its centre, what the jaws close on; symmetric under
  half turns about the handle, like the jaws themselves, so a grasp never turns the wrist by more than 90 degrees.
* ``nut_ring``: the ring alone (centre and corners; symmetric under quarter turns), what the peg holds.
* ``peg``: its bottom and top centres and the 4 top corners; symmetric under quarter turns.
* ``bin``: the 4 corners of its rim; symmetric under half turns.

The end effector's keypoint is the grip site's position (:func:`gripper_keypoints`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from kpflow.geometry.angles import yaw_of, yaw_rotation
from kpflow.policies.base import PolicyLayout
from kpflow.policies.phases import Grip, Phase, Phases
from kpflow.policies.symmetry import Symmetry, turn_permutation

from .specs import TaskSpec

# geometry (m), read from robosuite 1.5's models
CAN_RADIUS, CAN_HALF_HEIGHT = 0.025, 0.0407
NUT_RING_HALF = 0.0543  # centre to the ring's outer edge
NUT_HANDLE = (0.029, 0.079)  # the handle's extent along the nut's x axis
NUT_GRASP = 0.054  # where the jaws close on the handle (its centre), along the nut's x axis
NUT_HANDLE_HALF = (0.025, 0.0159, 0.01)  # half extents of the handle bar (the last: its top above its centre)
PEG_HALF, PEG_HEIGHT = 0.016, 0.1  # half side, and half length (its body origin is at its middle)
BIN_HALF = (0.195, 0.245)
SYMMETRY = {
    "cube": 4,
    "can": 0,
    "nut": 1,
    "nut_handle": 2,
    "nut_ring": 4,
    "peg": 4,
    "bin": 2,
}  # turns that leave it unchanged (0: any)


def reduced_yaw(yaw: float, order: int, reference: float) -> float:
    """``yaw`` plus the multiple of ``2 pi / order`` that brings it nearest ``reference`` (``order`` 1: as it is)."""
    period = 2 * np.pi / order
    return float(reference + (yaw - reference + period / 2) % period - period / 2)


def _square(centre, yaw: float, half_x: float, half_y: float, height: float = 0.0) -> list[np.ndarray]:
    """The 4 corners ``(+,+), (-,+), (-,-), (+,-)`` of a horizontal rectangle turned by ``yaw``, ``height`` above
    ``centre``."""
    r = yaw_rotation(yaw)
    return [
        np.asarray(centre) + r @ np.array([sx * half_x, sy * half_y, height])
        for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))
    ]


def _box(centre, yaw, half) -> np.ndarray:
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    return np.asarray(centre) + (signs * np.asarray(half)) @ yaw_rotation(yaw).T


def object_keypoints(
    kind: str, pos: np.ndarray, rot: np.ndarray, reference_yaw: float = 0.0, half: float | None = None
) -> np.ndarray:
    """The keypoints ``[N, 3]`` of an object of ``kind`` at body pose ``(pos, rot)`` (module docstring), symmetric
    ones ordered by the turn nearest ``reference_yaw``; ``half`` is a cube's half side."""
    order = SYMMETRY.get(kind)
    if order is None:
        raise ValueError(f"unknown keypoint kind {kind!r}; choose one of {sorted(SYMMETRY)}")
    yaw = reduced_yaw(yaw_of(rot), order, reference_yaw) if order else reference_yaw
    pos = np.asarray(pos, float)
    if kind == "cube":
        return _box(pos, yaw, (half, half, half))
    if kind == "can":
        ring = [
            pos + yaw_rotation(reference_yaw) @ (CAN_RADIUS * np.array([np.cos(a), np.sin(a), 0.0]))
            for a in np.arange(4) * np.pi / 2
        ]
        return np.stack([pos + [0, 0, CAN_HALF_HEIGHT], pos - [0, 0, CAN_HALF_HEIGHT], *ring])
    if kind == "nut_handle":
        centre = pos + yaw_rotation(yaw_of(rot)) @ np.array([NUT_GRASP, 0.0, 0.0])
        return np.stack([centre, *_square(centre, yaw, *NUT_HANDLE_HALF)])
    if kind in ("nut", "nut_ring"):
        handle = [pos + yaw_rotation(yaw) @ np.array([x, 0.0, 0.0]) for x in NUT_HANDLE] if kind == "nut" else []
        return np.stack([pos, *_square(pos, yaw, NUT_RING_HALF, NUT_RING_HALF), *handle])
    if kind == "peg":
        top = pos + [0, 0, PEG_HEIGHT]
        return np.stack([pos - [0, 0, PEG_HEIGHT], top, *_square(top, yaw, PEG_HALF, PEG_HALF)])
    return np.stack(_square(pos, yaw, *BIN_HALF))


@dataclass(frozen=True)
class ObjectPose:
    """An object's body pose, ``pos [3]`` and ``rot [3, 3]`` (world), and for a cube its ``half`` side (m)."""

    pos: np.ndarray
    rot: np.ndarray
    half: float | None = None


def object_pose(env, spec: TaskSpec, name: str) -> ObjectPose:
    """The simulator's pose of object or fixture ``name`` now."""
    pos, rot = env.object_pose(name)
    return ObjectPose(pos, rot, cube_half(env, name) if spec.kinds[name] == "cube" else None)


class SimulatorPoses:
    """Objects' poses read from the simulator (``keypoints=sim``): exact, and cheap enough to read every step."""

    per_step = True  #: read at every control step (a camera is read only where a policy decides)

    def reseed(self, *keys: int) -> None:
        """Nothing to seed: the simulator's poses are exact."""

    def poses(self, env, spec: TaskSpec, names: Sequence[str]) -> dict[str, ObjectPose]:
        return {n: object_pose(env, spec, n) for n in names}

    def grasped(self, env, name: str, at: tuple[np.ndarray, np.ndarray]) -> None:
        """Nothing to remember: a held object's pose is read like any other."""

    def released(self, name: str) -> None:
        """Nothing to forget."""


def pose_keypoints(
    spec: TaskSpec, name: str, pose: ObjectPose, reference_yaw: float = 0.0, kind: str | None = None
) -> np.ndarray:
    """:func:`object_keypoints` of object ``name`` at ``pose`` (``kind`` overrides the task's, e.g. ``nut_ring``)."""
    return object_keypoints(kind or spec.kinds[name], pose.pos, pose.rot, reference_yaw, pose.half)


def scene_keypoints(env, spec: TaskSpec, name: str, reference_yaw: float = 0.0, kind: str | None = None) -> np.ndarray:
    """Keypoints of object or fixture ``name`` in ``env`` now, from the simulator (``kind`` as in
    :func:`pose_keypoints`)."""
    return pose_keypoints(spec, name, object_pose(env, spec, name), reference_yaw, kind)


def cube_half(env, name: str, home: bool = False) -> float:
    """Half side (m) of cube ``name`` now (as the scene scaled it), from its collision geom; ``home``: as built."""
    model = env.sim.model
    body = env.object_body[name]
    geoms = [g for g in np.flatnonzero(model.geom_bodyid == body) if model.geom_contype[g]]
    sizes = env.geom_home[0] if home else model.geom_size
    return float(sizes[geoms[0]][0])


def in_hand_keypoints(env, spec: TaskSpec, reference_yaw: float, pose: ObjectPose | None = None) -> np.ndarray:
    """The held object's placement keypoints (:attr:`~.specs.TaskSpec.hand_kinds`) in the grip site's frame
    ``[N, 3]``, symmetric ones ordered by the turn nearest ``reference_yaw`` (the object's yaw relative to the
    jaws); the object at ``pose`` (None: the simulator's)."""
    ee_pos, ee_rot = env.ee_pose()
    pose = object_pose(env, spec, spec.grasp) if pose is None else pose
    world = pose_keypoints(spec, spec.grasp, pose, reference_yaw + yaw_of(ee_rot), spec.hand_kind)
    return (world - ee_pos) @ ee_rot


def gripper_keypoints(env) -> np.ndarray:
    """The grip site's position ``[1, 3]``."""
    return env.ee_pose()[0][None]


#: keypoints after the objects' in a policy's observation: the grip site and the two finger pads
GRIPPER_KEYPOINTS = 3
#: where the jaws close on an object of each kind: the segment between the means of these two sets of its keypoints
#: (a cube's centre, the can's axis from its top to its bottom, the square nut's handle from end to end)
GRASP_SEGMENT = {"cube": (tuple(range(8)), tuple(range(8))), "can": ((0,), (1,)), "nut": ((5,), (6,))}
#: the Panda's finger pads are 0.085 m apart open and 0.037-0.056 m closed on the nut's handle, a cube or the can; the
#: grasp segment is 0.3-0.6 cm (median) and at most 0.3-0.9 cm (95th percentile) from their midpoint when they are
#: closed on it (the released checkpoints' training data, per task)
PADS_CLOSED_BELOW, PADS_EMPTY_BELOW, GRASP_REACH = 0.07, 0.01, 0.025


def task_phases(spec: TaskSpec, groups: dict[str, tuple[int, ...]]) -> Phases:
    """The task's phases (:mod:`kpflow.policies.phases`) over the groups of :func:`policy_layout`: ``pick`` while
    the jaws do not hold the object (the map on the object to pick, the source searched relative to it, its goal
    not compared), then, for a task with a target, ``place`` while they do (the map on the target, the source
    searched relative to it, the held object pulled back with the gripper)."""
    pads, rows = groups["gripper"][1:], groups[spec.grasp]
    start, end = (tuple(rows[i] for i in ends) for ends in GRASP_SEGMENT[spec.kinds[spec.grasp]])
    grip = Grip((pads[0], pads[1]), start, end, PADS_CLOSED_BELOW, PADS_EMPTY_BELOW, GRASP_REACH)
    if spec.target is None:
        return Phases(grip, (Phase("pick", (spec.grasp,), (spec.grasp,), {"gripper": 4.0}),))
    pick = Phase("pick", (spec.grasp,), (spec.grasp,), {spec.target: 0.0, "gripper": 4.0}, holding=False)
    place = Phase("place", (spec.target,), (spec.target,), {"gripper": 4.0}, carried=(spec.grasp,), holding=True)
    return Phases(grip, (pick, place))


def task_symmetries(spec: TaskSpec, groups: dict[str, tuple[int, ...]]) -> tuple[Symmetry, ...]:
    """The relabellings of :func:`policy_keypoints` that leave the task as it was (:mod:`kpflow.policies.symmetry`):
    each turn of an observed object that :data:`SYMMETRY` says looks the same (a cube's and the square peg's
    quarter turns, the bin's half turn; the can's keypoints stand in fixed world directions, the nut's handle fixes
    its yaw), and the parallel jaws' half turn about their approach axis while they hold nothing (the finger pads
    swapped, the jaws turned by pi)."""
    k = sum(len(g) for g in groups.values())
    out = []
    for name in policy_objects(spec):
        order = SYMMETRY[spec.kinds[name]]
        points = object_keypoints(spec.kinds[name], np.zeros(3), np.eye(3), half=1.0)
        for turn in range(1, order if order > 1 else 1):
            local = turn_permutation(points, np.zeros(3), 2 * np.pi * turn / order)
            perm = list(range(k))
            for i, j in enumerate(local):
                perm[groups[name][i]] = groups[name][j]
            out.append(Symmetry(f"{name} turned {turn}/{order}", tuple(perm)))
    perm = list(range(k))
    pads = groups["gripper"][1:]
    perm[pads[0]], perm[pads[1]] = pads[1], pads[0]
    out.append(Symmetry("jaws turned 1/2", tuple(perm), tool_turn=np.pi, holding=False))
    return tuple(out)


def policy_layout(spec: TaskSpec, action_dim: int) -> PolicyLayout:
    """The layout of :func:`policy_keypoints` for ``spec``: the object picked (role ``objects``, named as in the
    task), its goal (``goals``: the target's keypoints, where the task has one) and ``gripper`` (``robot``: the grip
    site and the finger pads), all 3-D (counted on a unit pose); actions of ``action_dim`` values: position, 6-D
    rotation, gripper; its phases are :func:`task_phases`, its symmetries :func:`task_symmetries`, its transport defaults phase by phase."""
    groups, start = {}, 0
    for name in policy_objects(spec):
        n = len(object_keypoints(spec.kinds[name], np.zeros(3), np.eye(3), half=1.0))
        groups[name], start = tuple(range(start, start + n)), start + n
    groups["gripper"] = tuple(range(start, start + GRIPPER_KEYPOINTS))
    roles = {"objects": (spec.grasp,), "goals": (spec.target,) if spec.target else (), "robot": ("gripper",)}
    # transporting policies follow the phases (results/suite_policies.md); without them a map on the objects, the
    # gripper pulled back, not fitted
    transport = {"segments": True, "fit_on": ["objects", "goals"]}
    return PolicyLayout(start + GRIPPER_KEYPOINTS, 3, action_dim, groups, roles, rotation=True, phases=task_phases(spec, groups),
                        symmetries=task_symmetries(spec, groups), transport=transport)  # fmt: skip


def policy_objects(spec: TaskSpec) -> list[str]:
    """The objects a policy observes: the one to pick, then its goal (where the task has one)."""
    return [spec.grasp] + ([spec.target] if spec.target else [])


def policy_keypoints(env, spec: TaskSpec, poses: dict[str, ObjectPose] | None = None) -> np.ndarray:
    """What a policy observes ``[K, 3]``: the keypoints of the object to pick and of its goal (symmetric ones
    ordered by the turn nearest the jaws' yaw, as a grasp would choose) at ``poses`` (None: the simulator's), the
    grip site and the two finger pads (which carry the jaws' yaw and opening)."""
    jaws = yaw_of(env.ee_pose()[1])
    names = policy_objects(spec)
    poses = {n: object_pose(env, spec, n) for n in names} if poses is None else poses
    return np.concatenate(
        [pose_keypoints(spec, n, poses[n], jaws) for n in names] + [gripper_keypoints(env), env.finger_pads()]
    )
