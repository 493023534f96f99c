"""Keypoints of the benchmark tasks' objects, from the simulator's object pose and geometry.

A keypoint set names what a grasp or a placement depends on, and keeps the object's symmetries: a cube's eight
corners look the same after a quarter turn, so they are ordered by the cube's axis nearest a reference yaw (the
source scene's), not by its body frame; the transport then turns the gripper by at most 45 degrees, where an
object-frame transform turns it by the cube's full yaw. Each kind's keypoints (``[N, 3]``, world frame, m) are
declared in its own file of :mod:`.objects`: ``cube`` (the 8 corners), ``can`` (top, bottom and 4 rim points),
``nut``, ``nut_handle`` and ``nut_ring`` (the square nut), ``peg``, ``bin``.

The end effector's keypoint is the grip site's position (:func:`gripper_keypoints`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from kpflow.core.phases import Grip, Phase, Phases
from kpflow.core.policy import PolicyLayout
from kpflow.core.symmetry import Symmetry, turn_permutation
from kpflow.geometry.angles import yaw_of

from .objects import SYMMETRY, object_kind, reduced_yaw
from .objects.cube import cube_half
from .specs import TaskSpec


def object_keypoints(
    kind: str, pos: np.ndarray, rot: np.ndarray, reference_yaw: float = 0.0, half: float | None = None
) -> np.ndarray:
    """The keypoints ``[N, 3]`` of an object of ``kind`` at body pose ``(pos, rot)`` (module docstring; each kind's
    file of :mod:`.objects`), symmetric ones ordered by the turn nearest ``reference_yaw``; ``half`` is a cube's half
    side."""
    which = object_kind(kind)
    order = which.symmetry
    yaw = reduced_yaw(yaw_of(rot), order, reference_yaw) if order else reference_yaw
    return which.keypoints(np.asarray(pos, float), rot, yaw, reference_yaw, half)


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

    def released(self, env, name: str) -> None:
        """Nothing to forget."""

    def missed(self, name: str) -> None:
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
    """The task's phases (:mod:`kpflow.core.phases`) over the groups of :func:`policy_layout`: ``pick`` while
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
    """The relabellings of :func:`policy_keypoints` that leave the task as it was (:mod:`kpflow.core.symmetry`):
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
