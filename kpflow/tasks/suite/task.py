"""A robosuite benchmark task behind one class: a :class:`~kpflow.core.task.GymTask` (its closed loop runs in
:class:`~.gym_env.SuiteGymEnv`), scenes, the scripted source demonstration recorded segment by segment, what is
observed at a segment's start, and running a segment.

A source demonstration is a list of :class:`~kpflow.core.task.Segment`: each holds the commanded trajectory and
what the scene looked like when it began (every object's pose, the keypoints that the segment depends on, the grip
site), so a generator (:mod:`kpflow.generation.segment_transport`) can carry it into a new scene once that segment's
start is reached there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kpflow.core.task import EvaluationScene, GymTask, Segment, SegmentStart
from kpflow.geometry.angles import yaw_of
from kpflow.geometry.rotations import matrix_to_rot6d
from kpflow.trajectory import Trajectory
from kpflow.vision.keypoint_source import KeypointSource

from .arm_limits import SuiteArmLimits, path_cost
from .demonstrator import plan_segment
from .env import CLOSED, OPEN, SuiteEnv
from .gym_env import ACTION_DIM, SuiteGymEnv
from .keypoints import (
    SimulatorPoses,
    gripper_keypoints,
    in_hand_keypoints,
    policy_keypoints,
    policy_layout,
    pose_keypoints,
)
from .objects import SYMMETRY
from .perception import CameraKeypoints
from .scene import Scene, sample_scene
from .specs import task_spec

TRACKING_LIMIT = (
    0.03  # m between the commanded and the measured grip site at a segment's end: the arm did not get there
)
JOINT_MARGIN = 0.02  # rad from a joint's range: the arm is at its limit
HOLD_STEPS = 10  # control steps holding the last pose before robosuite's success test


@dataclass(frozen=True)
class SegmentRun:
    """How one segment went: the measured grip site ``tip [T, 3]``, the robosuite ``states [T, S]`` (MuJoCo's
    flattened state before each step), the ``keypoints [T, K, 3]`` a policy observes then
    (:func:`~.keypoints.policy_keypoints`), the ``actions [T, 7]`` sent to robosuite and the same as ``ee_targets
    [T, 10]`` (position, 6-D rotation, gripper: what a policy predicts), and ``failure`` (None or the reason)."""

    tip: np.ndarray
    states: np.ndarray
    keypoints: np.ndarray
    actions: np.ndarray
    ee_targets: np.ndarray
    failure: str | None


#: the evaluation scenes' stream offset: scene ``i`` of a variant for run seed ``s`` is keyed ``(EVALUATION_STREAM + s, variant,
#: i)``, which neither the source demonstrations (``SOURCE_SEED``) nor the generated ones (``seed``) use
EVALUATION_STREAM = 20_000


class SuiteTask(GymTask):
    """robosuite's ``lift``, ``stack``, ``can`` or ``square`` (:data:`~.specs.TASKS`) with the Panda; its objects'
    keypoints from the simulator or from cameras (``keypoints``, :class:`~kpflow.vision.keypoint_source.KeypointSource`;
    None: the simulator's). Its conditions are the variants (``d0``: robosuite's placement as it ships; ``wide``, ...);
    an evaluation episode may take 500 control steps and scores robosuite's own success."""

    max_steps = 500

    def __init__(self, name: str = "lift", keypoints: KeypointSource | None = None):
        self.spec = task_spec(name)
        self.name = self.spec.name
        self.conditions = self.spec.variants
        self._layout = policy_layout(self.spec, ACTION_DIM)
        self.keypoints = keypoints or KeypointSource()
        #: reads the objects' poses: :class:`~.keypoints.SimulatorPoses` or :class:`~.perception.CameraKeypoints`
        self.perception = CameraKeypoints.from_source(self.keypoints) if self.keypoints.camera else SimulatorPoses()
        self._sims: dict[bool, SuiteEnv] = {}  # render -> the simulator the Gymnasium envs share

    def __getstate__(self) -> dict:  # a worker builds its own simulators
        return {**self.__dict__, "_sims": {}}

    @property
    def policy_layout(self):
        """What its learned policies observe and return (:func:`~.keypoints.policy_layout`)."""
        return self._layout

    @property
    def arm_limits(self) -> SuiteArmLimits:
        """The Panda's limits a policy checks its chunks against (:class:`~.arm_limits.SuiteArmLimits`)."""
        return SuiteArmLimits(self._layout.groups["gripper"][1:])

    def make_sim(self, render: bool = False) -> SuiteEnv:
        """A simulator for this task (rendering when asked, or when its keypoints come from cameras, whose names are
        checked against the model's here: an unknown camera is refused before any episode)."""
        env = SuiteEnv(self.spec, render=render or self.keypoints.camera)
        if isinstance(self.perception, CameraKeypoints):
            self.perception.cameras.check_names(env)
        return env

    def make_env(self, condition: str, render: bool = False) -> SuiteGymEnv:
        """The Gymnasium env of ``condition``'s scenes (:class:`~.gym_env.SuiteGymEnv`), its objects read by
        :attr:`perception`. Building robosuite's model takes seconds, and a rendering one freed while another renders
        breaks that one, so the envs of a task share one :meth:`make_sim` (per ``render``), which every reset sets up
        afresh (:meth:`~.env.SuiteEnv.reset_to`)."""
        self.check_condition(condition)
        if render not in self._sims:
            self._sims[render] = self.make_sim(render)
        return SuiteGymEnv(
            self._sims[render], condition, self._layout.n_keypoints, self.perception, "rgb_array" if render else None
        )

    def evaluation_scene(self, condition: str, index: int, seed: int) -> EvaluationScene:
        """Scene ``index`` of ``condition`` in the stream ``EVALUATION_STREAM + seed``; the policy and the perception reset
        with ``index``; the scene recorded is the env's (reset's ``info["scene"]``)."""
        return EvaluationScene(
            {"seed": int(index), "options": {"stream": EVALUATION_STREAM + int(seed)}}, int(index), {}
        )

    def score(self, episode) -> tuple[bool, str | None, dict]:
        """robosuite's success; the failure ``"not perceived"`` (the cameras never placed the objects) or ``"time
        limit"``; the steps, decisions and the reads that could not place an object; on a perception other than the
        simulator's, each stage's largest keypoint error (``error_<stage>_mm``, :mod:`.perception_errors`)."""
        failure = episode.first_info.get("failure") or (None if episode.success else "time limit")
        scores = {
            "steps": episode.steps,
            "decisions": episode.decisions,
            "unseen_reads": int(episode.info.get("unseen_reads", 0)),
            **({"occluded_reads": int(episode.info["occluded_reads"])} if "occluded_reads" in episode.info else {}),
            **episode.info.get("perception_errors", {}),
        }
        return episode.success, failure, scores

    def describe(self) -> dict:
        return {"keypoints": self.keypoints.kind}

    def sample_scene(self, env: SuiteEnv, variant: str, index: int, seed: int = 0) -> Scene:
        return sample_scene(self.spec, env, variant, index, seed)

    # ------------------------------------------------------------------------------------------ observing
    def reference_object(self, segment: str) -> str:
        """The object a segment acts relative to: the one picked, or the goal of a place."""
        return self.spec.grasp if segment == "pick" else self.spec.target

    def observe(self, env: SuiteEnv, segment: str, reference: SegmentStart | None = None) -> SegmentStart:
        """What ``segment`` depends on, now (:class:`~kpflow.core.task.SegmentStart`): for a pick the grasp
        keypoints of the object picked, for a place the goal's keypoints and the held object's in the hand
        (:func:`~.keypoints.in_hand_keypoints`; ``yaws["hand"]`` is its yaw relative to the jaws), and the arm's
        :func:`~.arm_limits.path_cost`. Symmetric keypoints are ordered by the turn nearest the ``reference``
        start's yaws (the recorded source's; its own without one). The poses of the reference object and of the one
        picked come from :attr:`perception` (the simulator, or one capture of the cameras)."""
        spec = self.spec
        name = self.reference_object(segment)
        seen = self.perception.poses(env, spec, list(dict.fromkeys((name, spec.grasp))))
        poses = {n: (p.pos, p.rot) for n, p in seen.items()}
        yaws = {n: yaw_of(r) for n, (_, r) in poses.items()}
        yaws["hand"] = yaws[spec.grasp] - yaw_of(env.ee_pose()[1])
        ref = reference.yaws if reference is not None else yaws
        keypoints = {
            name: pose_keypoints(spec, name, seen[name], ref[name], spec.grasp_kind if segment == "pick" else None)
        }
        in_hand = None
        if segment == "place":
            order = max(SYMMETRY[spec.hand_kind], 1)
            turns = [ref["hand"] + 2 * np.pi * k / order for k in range(order)]
            in_hand = np.stack([in_hand_keypoints(env, spec, turn, seen[spec.grasp]) for turn in turns])
        return SegmentStart(poses, keypoints, yaws, gripper_keypoints(env), in_hand, path_cost(env))

    # ------------------------------------------------------------------------------------------ acting
    def run_segment(
        self, env: SuiteEnv, trajectory: Trajectory, frames: list | None = None, frame_every: int = 2
    ) -> SegmentRun:
        """Command every step of ``trajectory`` and say whether the arm got there. The keypoints recorded at every
        step (what a policy trained on the episode observes) are the simulator's whatever :attr:`perception` is: a
        camera capture per control step would cost about a second each."""
        tip, states, keypoints, actions = [], [], [], []
        for t in range(len(trajectory)):
            states.append(env.sim.get_state().flatten())
            keypoints.append(policy_keypoints(env, self.spec))
            if t and trajectory.grasp[t] and not trajectory.grasp[t - 1]:  # the jaws close on the object
                self.perception.grasped(env, self.spec.grasp, (trajectory.positions[t], trajectory.rotations[t]))
            elif t and trajectory.grasp[t - 1] and not trajectory.grasp[t]:  # they let it go
                self.perception.released(env, self.spec.grasp)
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
        targets = np.concatenate(
            [trajectory.positions, matrix_to_rot6d(trajectory.rotations), np.array(actions)[:, 6:]], axis=1
        )
        return SegmentRun(tip, np.array(states), np.array(keypoints), np.array(actions), targets, failure)

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
            start = self.observe(env, name)
            trajectory = plan_segment(env, self.spec, name, home_yaw)
            run = self.run_segment(env, trajectory)
            segments.append(Segment(name, trajectory, start))
            failure = run.failure or self.segment_failure(env, name)
            if failure:
                return segments, False, failure
        success, failure = self.finish(env, segments[-1].trajectory)
        return segments, success, failure
