"""Reach: move a point agent onto a square target in the unit square.

Keypoints (5, 2-D): the target's four corners, then the agent. Actions (2-D): the agent's next position target; the
agent moves towards it by at most ``SPEED`` per step. Success: the agent within ``TOLERANCE`` of the target's centre.
Conditions: ``default`` (targets in the middle of the square) and ``wide`` (targets anywhere).
"""

import gymnasium as gym
import numpy as np

from kpflow.core.policy import PolicyLayout
from kpflow.core.task import GymTask

SPEED, TOLERANCE, HALF_SIDE = 0.05, 0.03, 0.05
TARGET_RANGE = {"default": (0.35, 0.65), "wide": (0.1, 0.9)}


class ReachEnv(gym.Env):
    """The simulator: observations ``{"keypoints": [5, 2]}``, actions ``[2]``, ``info["is_success"]``."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, condition: str = "default", render_mode: str | None = None):
        self.low, self.high = TARGET_RANGE[condition]
        self.render_mode = render_mode
        self.observation_space = gym.spaces.Dict({"keypoints": gym.spaces.Box(-1.0, 2.0, (5, 2), np.float64)})
        self.action_space = gym.spaces.Box(0.0, 1.0, (2,), np.float64)

    def _obs(self) -> dict:
        corners = self.target + HALF_SIDE * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
        return {"keypoints": np.vstack([corners, self.agent])}

    def reset(self, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.target = self.np_random.uniform(self.low, self.high, 2)
        self.agent = self.np_random.uniform(0.0, 1.0, 2)
        return self._obs(), {"is_success": False}

    def step(self, action):
        action = np.asarray(action, np.float64)
        if action.shape != (2,) or not np.isfinite(action).all():  # what kpflow's envs refuse: never move on NaN
            raise ValueError(f"action must be 2 finite numbers (a target x, y in [0, 1]), got {action.tolist()!r}")
        move = np.clip(action, 0.0, 1.0) - self.agent  # a target outside the space is clipped to it
        self.agent = self.agent + move * min(1.0, SPEED / max(np.linalg.norm(move), 1e-12))
        success = bool(np.linalg.norm(self.agent - self.target) < TOLERANCE)
        return self._obs(), float(success), success, False, {"is_success": success}

    def render(self) -> np.ndarray:
        side = 96
        image = np.full((side, side, 3), 255, np.uint8)
        (x0, y0), (x1, y1) = (((self.target + s * HALF_SIDE) * side).astype(int) for s in (-1, 1))
        image[max(y0, 0) : y1, max(x0, 0) : x1] = (90, 160, 90)
        ax, ay = np.clip((self.agent * side).astype(int), 2, side - 3)
        image[ay - 2 : ay + 3, ax - 2 : ax + 3] = (40, 60, 200)
        return image


class ReachExpert:
    """The scripted demonstrator: a chunk of 8 targets along the straight line to the target's centre."""

    n_obs, execute = 1, 8

    def reset(self, seed: int | None = None) -> None:
        pass

    def act(self, obs: dict) -> np.ndarray:
        keypoints = np.asarray(obs["keypoints"])
        agent, centre = keypoints[4], keypoints[:4].mean(axis=0)
        step = (centre - agent) * min(1.0, SPEED / max(np.linalg.norm(centre - agent), 1e-12))
        return np.array([agent + step * min(k, np.linalg.norm(centre - agent) / SPEED) for k in range(1, 9)])


class ReachTask(GymTask):
    """The task contract (kpflow.core.task.GymTask) around :class:`ReachEnv` and :class:`ReachExpert`."""

    name = "reach"
    conditions = ("default", "wide")
    max_steps = 60

    @property
    def policy_layout(self) -> PolicyLayout:
        return PolicyLayout(
            5,
            2,
            2,
            groups={"target": (0, 1, 2, 3), "agent": (4,)},
            roles={"objects": ("target",), "goals": (), "robot": ("agent",)},
        )

    def make_env(self, condition: str = "default", render: bool = False) -> ReachEnv:
        self.check_condition(condition)
        return ReachEnv(condition, "rgb_array" if render else None)

    def expert(self) -> ReachExpert:
        return ReachExpert()
