"""A robosuite benchmark task behind one class: scenes, the scripted source demonstration recorded segment by
segment, what is observed at a segment's start, and running a segment.

A source demonstration is a list of :class:`~kpflow.tasks.base.Segment`: each holds the commanded trajectory and
what the scene looked like when it began (every object's pose, the keypoints that the segment depends on, the grip
site), so a generator (:mod:`kpflow.policies.segment_transport`) can carry it into a new scene once that segment's
start is reached there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kpflow.tasks.base import Segment, Trajectory

from .demonstrator import plan_segment
from .env import CLOSED, OPEN, SuiteEnv
from .keypoints import gripper_keypoints, scene_keypoints, yaw_of
from .scene import VARIANTS, Scene, sample_scene
from .specs import task_spec

TRACKING_LIMIT = 0.03  # m between the commanded and the measured grip site at a segment's end: the arm did not get there
JOINT_MARGIN = 0.02  # rad from a joint's range: the arm is at its limit
HOLD_STEPS = 10  # control steps holding the last pose before robosuite's success test


@dataclass(frozen=True)
class SegmentRun:
    """How one segment went: the measured grip site ``tip [T, 3]``, the robosuite ``states [T, S]`` (MuJoCo's
    flattened state before each step) and ``actions [T, 7]`` it took, and ``failure`` (None or the reason)."""

    tip: np.ndarray
    states: np.ndarray
    actions: np.ndarray
    failure: str | None


class SuiteTask:
    """robosuite's ``lift``, ``stack``, ``can`` or ``square`` (:data:`~.specs.TASKS`) with the Panda."""

    def __init__(self, name: str = "lift"):
        self.spec = task_spec(name)
        self.name = self.spec.name
        self.variants = VARIANTS

    def make_env(self, render: bool = False) -> SuiteEnv:
        return SuiteEnv(self.spec, render=render)

    def sample_scene(self, env: SuiteEnv, variant: str, index: int, seed: int = 0) -> Scene:
        return sample_scene(self.spec, env.env, variant, index, seed)

    # ------------------------------------------------------------------------------------------ observing
    def segment_objects(self, segment: str) -> tuple[str, ...]:
        """The objects a segment's keypoints come from: the one picked, or the goal and the object held."""
        return (self.spec.grasp,) if segment == "pick" else (self.spec.target, self.spec.grasp)

    def observe(self, env: SuiteEnv, segment: str, reference: Segment | None = None) -> dict:
        """What a segment depends on, now: ``poses`` (every object and fixture: (position, rotation)), ``keypoints``
        (object -> ``[N, 3]``, symmetric ones ordered by the turn nearest the ``reference`` segment's yaws),
        ``yaws`` and the ``gripper`` keypoint ``[1, 3]``."""
        names = (*self.spec.object_bodies, *self.spec.fixture_bodies)
        poses = {n: env.object_pose(n) for n in names}
        yaws = {n: yaw_of(r) for n, (_, r) in poses.items()}
        keypoints = {
            n: scene_keypoints(env, self.spec, n, reference.yaws[n] if reference is not None else yaws[n])
            for n in self.segment_objects(segment)
        }
        return {"poses": poses, "keypoints": keypoints, "yaws": yaws, "gripper": gripper_keypoints(env)}

    # ------------------------------------------------------------------------------------------ acting
    def run_segment(self, env: SuiteEnv, trajectory: Trajectory, frames: list | None = None, frame_every: int = 2) -> SegmentRun:
        """Command every step of ``trajectory`` and say whether the arm got there."""
        tip, states, actions = [], [], []
        for t in range(len(trajectory)):
            states.append(env.sim.get_state().flatten())
            gripper = CLOSED if trajectory.grasp[t] else OPEN
            env.command(trajectory.positions[t], trajectory.rotations[t], gripper)
            actions.append(env.last_action.copy())
            tip.append(env.ee_pose()[0])
            if frames is not None and t % frame_every == 0:
                frames.append(env.render_view())
        tip = np.array(tip)
        failure = None
        q, limits = env.arm_joints(), env.joint_limits
        if np.any((q < limits[:, 0] + JOINT_MARGIN) | (q > limits[:, 1] - JOINT_MARGIN)):
            failure = "joint limit"
        elif np.linalg.norm(tip[-1] - trajectory.positions[-1]) > TRACKING_LIMIT:
            failure = "unreachable"
        return SegmentRun(tip, np.array(states), np.array(actions), failure)

    def segment_failure(self, env: SuiteEnv, segment: str) -> str | None:
        """After ``segment`` ran: ``"not grasped"`` when the pick left the object out of the jaws."""
        if segment == "pick" and not env.grasping(self.spec.grasp):
            return "not grasped"
        return None

    def finish(self, env: SuiteEnv, last: Trajectory) -> tuple[bool, str | None]:
        """Hold the last pose, then robosuite's success test; the failure reason of a finished attempt."""
        for _ in range(HOLD_STEPS):
            env.command(last.positions[-1], last.rotations[-1], CLOSED if last.grasp[-1] else OPEN)
        if env.success():
            return True, None
        return False, "not lifted" if self.spec.target is None else "not placed"

    def demonstrate(self, env: SuiteEnv, scene: Scene) -> tuple[list[Segment], bool, str | None]:
        """The scripted demonstration in ``scene``: its segments, success and failure reason."""
        env.reset_to(scene)
        home_yaw = yaw_of(env.home_pose[1])
        segments = []
        for name in self.spec.segments:
            seen = self.observe(env, name)
            trajectory = plan_segment(env, self.spec, name, home_yaw)
            run = self.run_segment(env, trajectory)
            segments.append(Segment(name, trajectory, seen["poses"], seen["keypoints"], seen["yaws"], seen["gripper"]))
            failure = run.failure or self.segment_failure(env, name)
            if failure:
                return segments, False, failure
        success, failure = self.finish(env, segments[-1].trajectory)
        return segments, success, failure
