"""A robosuite benchmark task as a Gymnasium env: what the one closed loop (:func:`kpflow.core.rollout.rollout`)
runs a policy in.

``reset(seed=i, options={"stream": s})`` sets up scene ``i`` of the env's variant in scene stream ``s`` (without a
seed, a scene drawn from the env's generator)
(:func:`~.scene.sample_scene`: the key ``(s, variant, i)``) and restarts the perception's noise at ``i``;
``info["scene"]`` is the scene as a dict. Observations are ``{"keypoints": [K, 3], "joints": [7]}``
(:func:`~.keypoints.policy_keypoints`, and the arm's joint angles, which a policy checks its chunks against:
:class:`~.arm_limits.SuiteArmLimits`): the gripper's from the robot, the objects' from the perception (the
simulator's at every step; a camera's only where the loop says a decision will read the observation,
:meth:`SuiteGymEnv.will_read`, held in between; an object the cameras cannot place in a read keeps its last seen pose;
the object picked, once the jaws close on it, is carried with them from where it was last seen, until they open or
close on nothing: their finger pads nearer than the empty jaws' ``PADS_EMPTY_BELOW``). An action is an
end-effector target ``[10]``: position, 6-D rotation (:func:`kpflow.geometry.rotations.rot6d_to_matrix`) and the
gripper (closed when > 0); a step refuses an action that is not 10 finite numbers or names no rotation, and clips
the position to the action space (:meth:`SuiteGymEnv.checked_action`). ``info["is_success"]`` is robosuite's own check; ``info["unseen_reads"]`` counts the reads
that could not place an object; with a perception other than the simulator's, ``info["occluded_reads"]`` those it
refused as partly hidden (:mod:`kpflow.vision.occlusion`) and ``info["perception_errors"]`` is
each stage's largest keypoint error so far against the simulator's (:mod:`.perception_errors`: the object before
and at the grasp, in the hand, the goal, the placement at the release). When the first read places nothing, reset's ``info["failure"]`` is ``"not
perceived"`` and the loop ends the episode before any step.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from kpflow.geometry.rotations import rot6d_to_matrix

from .env import CLOSED, OPEN, SuiteEnv
from .keypoints import PADS_EMPTY_BELOW, SimulatorPoses, object_pose, policy_keypoints, policy_objects
from .perception_errors import PerceptionErrors, keypoint_error_mm, relative_error_mm
from .scene import sample_scene

ACTION_DIM = 10  #: position [3], 6-D rotation [6], gripper [1]
ARM_JOINTS = 7  #: the Panda's arm joints (rad), observed beside the keypoints
WORKSPACE_M = 2.0  #: the action space's bound on a target position's coordinates (m, world frame)


class SuiteGymEnv(gym.Env):
    """Scenes of ``variant`` of ``sim``'s task (module docstring), the objects' poses read by ``perception``
    (:class:`~.keypoints.SimulatorPoses` when None); ``n_keypoints`` the policy layout's count."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, sim: SuiteEnv, variant: str, n_keypoints: int, perception=None, render_mode: str | None = None):
        if variant not in sim.spec.variants:
            raise ValueError(f"{sim.spec.name} has no variant {variant!r}; choose from {', '.join(sim.spec.variants)}")
        self.sim, self.variant, self.render_mode = sim, variant, render_mode
        self.perception = SimulatorPoses() if perception is None else perception
        self.observation_space = gym.spaces.Dict({"keypoints": gym.spaces.Box(-np.inf, np.inf, (n_keypoints, 3), np.float64),
                                                  "joints": gym.spaces.Box(*sim.joint_limits.T, (ARM_JOINTS,), np.float64)})  # fmt: skip
        bound = np.array(
            [WORKSPACE_M] * 3 + [1.0] * 7
        )  # a position in the world (m), a 6-D rotation's columns, the gripper
        self.action_space = gym.spaces.Box(-bound, bound, (ACTION_DIM,), np.float64)
        self._names = policy_objects(sim.spec)
        self._poses, self._read, self._closed, self._unseen, self._obs = None, True, False, 0, None
        self._held = False  # the perception carries the object to pick with the jaws
        #: compared with the simulator's poses at every read (:mod:`.perception_errors`); None: the simulator's own
        self._errors = None if isinstance(self.perception, SimulatorPoses) else PerceptionErrors()

    def will_read(self, read: bool) -> None:
        """Whether the observation the next step returns will be read by a decision (the loop says, before each step);
        a camera is read only then, a simulator's poses at every step."""
        self._read = bool(read)

    def _observe(self) -> dict:
        if self._poses is None or self.perception.per_step or self._read:
            try:
                self._poses = self.perception.poses(self.sim, self.sim.spec, self._names)
            except ValueError:  # an object hidden (by the arm, the jaws) in this read: keep what was seen last
                self._unseen += 1
            else:
                self._audit_read()
        if self._poses is None:
            keypoints = np.full(self.observation_space["keypoints"].shape, np.nan)
        else:
            keypoints = policy_keypoints(self.sim, self.sim.spec, self._poses)
        self._obs = {"keypoints": keypoints, "joints": self.sim.arm_joints()}
        return self._obs

    def _true(self) -> dict:
        return {n: object_pose(self.sim, self.sim.spec, n) for n in self._names}

    def _audit_read(self) -> None:
        """Each object's read against the simulator's, in its stage (:mod:`.perception_errors`)."""
        if self._errors is None:
            return
        spec, true = self.sim.spec, self._true()
        for name in self._names:
            stage = ("held" if self._held else "pick") if name == spec.grasp else "goal"
            self._errors.add(stage, keypoint_error_mm(spec, name, self._poses[name], true[name]))

    def _audit_jaws(self, closing: bool) -> None:
        """At the step the jaws close, the object to pick as last seen; as they open, the placement."""
        if self._errors is None or self._poses is None:
            return
        spec, true = self.sim.spec, self._true()
        if closing:
            self._errors.add("grasp", keypoint_error_mm(spec, spec.grasp, self._poses[spec.grasp], true[spec.grasp]))
        elif spec.target is not None:
            self._errors.add("place", relative_error_mm(spec, spec.grasp, spec.target, self._poses, true))

    def _info(self, **extra) -> dict:
        errors = (
            {}
            if self._errors is None
            else {"perception_errors": self._errors.summary(), "occluded_reads": self.perception.occluded}
        )
        return {"is_success": self.sim.success(), "unseen_reads": self._unseen, **errors, **extra}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        # seed=i is scene i; without one, the env's generator (seeded by the last seed given) picks the scene
        index = int(seed) if seed is not None else int(self.np_random.integers(2**31))
        stream = int((options or {}).get("stream", 0))
        scene = sample_scene(self.sim.spec, self.sim, self.variant, index, stream)
        self.sim.reset_to(scene)
        self.perception.reseed(index)
        self._poses, self._read, self._closed, self._unseen, self._held = None, True, False, 0, False
        self._errors = None if self._errors is None else PerceptionErrors()
        obs = self._observe()
        extra = {"failure": "not perceived"} if self._poses is None else {}
        return obs, self._info(scene=scene.as_dict(), **extra)

    def checked_action(self, action) -> tuple[np.ndarray, np.ndarray, bool]:
        """``action`` as ``(position [3], rotation [3, 3], closing)``, or ``ValueError`` saying what is wrong: it must be
        10 finite numbers, and its 6-D rotation two columns neither zero nor parallel. The position is clipped to
        the action space's bound (Push-T's env clips its targets to the arena the same way), so no target beyond it,
        and nothing non-finite, ever reaches robosuite."""
        try:
            a = np.asarray(action, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            a = None
        if a is None or a.shape != (ACTION_DIM,) or not np.isfinite(a).all():
            raise ValueError(
                f"action must be {ACTION_DIM} finite numbers (position [3], 6-D rotation [6], gripper [1]), got {action!r}"
            )
        first, second = a[3:6], a[6:9]
        n1 = np.linalg.norm(first)
        if n1 < 1e-9 or np.linalg.norm(second - (first @ second) / n1**2 * first) < 1e-9 * max(
            1.0, np.linalg.norm(second)
        ):
            raise ValueError(
                f"action's 6-D rotation {a[3:9].tolist()} has a zero column or two parallel ones: it names no rotation"
            )
        return np.clip(a[:3], -WORKSPACE_M, WORKSPACE_M), rot6d_to_matrix(a[3:9]), bool(a[9] > 0)

    def step(self, action):
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        position, rotation, closing = self.checked_action(action)
        target = (position, rotation)
        grasp = self.sim.spec.grasp
        if closing and not self._closed:  # the jaws close on the object to pick: a camera carries its pose with them
            self._audit_jaws(True)
            self.perception.grasped(self.sim, grasp, target)
            self._held = True
        elif self._closed and not closing:
            if self._held:
                self._audit_jaws(False)
            self.perception.released(self.sim, grasp)
            self._held = False
        self._closed = closing
        self.sim.command(*target, CLOSED if closing else OPEN)
        if self._held and np.linalg.norm(np.subtract(*self.sim.finger_pads())) < PADS_EMPTY_BELOW:
            self.perception.missed(grasp)  # the jaws closed on nothing: the object is where the cameras saw it
            self._held = False
        info = self._info()
        obs = self._obs if info["is_success"] else self._observe()  # the episode is over: nothing more to read
        return obs, float(info["is_success"]), info["is_success"], False, info

    def render(self):
        return self.sim.render_view() if self.render_mode == "rgb_array" else None
