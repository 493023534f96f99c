"""The scripted source demonstrations of the benchmark tasks: each segment planned from the simulator's state at its
start, from the objects' geometry.

* ``pick`` (every task): over the grasp point, straight down, close the jaws, lift. The jaws close across the
  object: across a cube's faces (the face pair nearest the arm's home yaw), across the can at the home yaw, across
  the square nut's handle (``NUT_GRASP`` along its x axis, :mod:`.objects.nut`; of the two ways round, the one nearer the home yaw).
* ``place`` (stack, can, square): carry the held object over its goal at a safe height, lower it, open, retreat
  upwards. Its goal comes from where the object is in the hand now: cube A's centre on top of cube B; the can over
  its quarter of the target bin; the nut's ring centred over the peg, its square aligned with the peg's by the
  turn that :func:`~.arm_limits.path_cost` rates best (within ``MAX_PLACE_TURN`` and the last joint's range, nearest the
  robot's base): with the handle pointing away, the peg is at the edge of the Panda's reach.

Poses are the grip site's (between the finger pads), as :class:`~kpflow.trajectory.Trajectory` rows in the
interpolated straight segments of :func:`kpflow.tasks.arm.motion.segments_to_trajectory`; ``grasp`` is the jaws'
command (closed while True).
"""

from __future__ import annotations

import numpy as np

from kpflow.geometry.angles import yaw_rotation
from kpflow.tasks.arm.motion import segments_to_trajectory
from kpflow.trajectory import Trajectory

from .objects import object_kind
from .specs import TaskSpec

APPROACH = 0.10  # m above the grasp point before going down
LIFT = 0.12  # m the object is lifted after the grasp
CLOSE_STEPS = 12  # control steps holding still while the jaws close (and open)
RETREAT = {"cubeB": 0.12, "bin": 0.06, "peg": 0.12}  # m up after opening
CARRY_CLEARANCE = {
    "cubeB": 0.06,
    "bin": 0.14,
    "peg": 0.20,
}  # m of the held object's centre above its goal while carried
RELEASE_HEIGHT = {"cubeB": 0.004, "bin": 0.09, "peg": 0.03}  # m above the goal (see plan_place) at which the jaws open


def jaws_down(yaw: float) -> np.ndarray:
    """The gripper pointing down with its jaws closing along the world direction ``yaw``: the rotation of
    :func:`kpflow.tasks.arm.motion.pointing_down`, computed as a product of exact matrices. The two differ by
    1e-16, and Square's contacts amplify that: one attempt in 30 changed outcome with ``pointing_down``, so the
    generated demonstrations of results/generation.md are reproduced with this one."""
    return yaw_rotation(yaw) @ np.diag([1.0, -1.0, -1.0])


def grasp_pose(env, spec: TaskSpec, home_yaw: float) -> tuple[np.ndarray, float]:
    """Where the jaws close on ``spec.grasp`` now: the grip site's position and the jaws' yaw (its kind's
    :meth:`~.objects.base.ObjectKind.grasp`)."""
    pos, rot = env.object_pose(spec.grasp)
    return object_kind(spec.kinds[spec.grasp]).grasp(env, pos, rot, home_yaw)


def plan_pick(env, spec: TaskSpec, home_yaw: float) -> Trajectory:
    """The pick segment from the arm's pose now (module docstring)."""
    start_pos, start_rot = env.ee_pose()
    grasp, yaw = grasp_pose(env, spec, home_yaw)
    rot = jaws_down(yaw)
    above = grasp + [0.0, 0.0, APPROACH]
    segments = [  # (phase, target, rotation, settle steps, jaws closed)
        ("approach", above, rot, 8, False),
        ("descend", grasp, rot, 8, False),
        ("close", grasp, rot, CLOSE_STEPS, True),
        ("lift", grasp + [0.0, 0.0, LIFT], rot, 5, True),
    ]
    return segments_to_trajectory(start_pos, start_rot, segments)


def place_goal(env, spec: TaskSpec) -> tuple[np.ndarray, float]:
    """The held object's goal: the position of its body and the yaw change that gets it there (module docstring; the
    target's kind's :meth:`~.objects.base.ObjectKind.place_goal`)."""
    held, goal = env.object_pose(spec.grasp), env.object_pose(spec.target)
    return object_kind(spec.kinds[spec.target]).place_goal(env, spec, held, goal)


def plan_place(env, spec: TaskSpec) -> Trajectory:
    """The place segment from the arm's pose now, carrying the object it holds (module docstring)."""
    start_pos, start_rot = env.ee_pose()
    held, _ = env.object_pose(spec.grasp)
    goal, turn = place_goal(env, spec)
    rz = yaw_rotation(turn)
    rot = rz @ start_rot
    offset = rz @ (start_pos - held)  # the grip site seen from the held object, after the turn
    clearance, release = CARRY_CLEARANCE[spec.target], RELEASE_HEIGHT[spec.target]
    carry = goal + offset + [0.0, 0.0, clearance]
    carry[2] = max(carry[2], start_pos[2])
    lower = goal + offset + [0.0, 0.0, release]
    segments = [
        ("carry", carry, rot, 25, True),
        ("lower", lower, rot, 8, True),
        ("open", lower, rot, CLOSE_STEPS, False),
        ("retreat", lower + [0.0, 0.0, RETREAT[spec.target]], rot, 10, False),
    ]
    return segments_to_trajectory(start_pos, start_rot, segments)


def plan_segment(env, spec: TaskSpec, segment: str, home_yaw: float) -> Trajectory:
    """The scripted ``segment`` (``"pick"`` or ``"place"``) from the state now."""
    if segment == "pick":
        return plan_pick(env, spec, home_yaw)
    if segment == "place":
        return plan_place(env, spec)
    raise ValueError(f"unknown segment {segment!r}; the task has {spec.segments}")
