"""The Push-T environment: standard physics, 25 keypoints, Gymnasium API."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from .geometry import N_KEYPOINTS, OUTLINE, T_KEYPOINTS, outline_coverage, t_keypoints, t_polygon, to_world
from .physics import DT, PushTPhysics
from .render import render_scene
from .splits import FIXED_GOAL, GOAL_MODES, SPLITS, Config, sample_config
from .workspace import get_workspace

_BODY_POINTS = np.concatenate([T_KEYPOINTS, OUTLINE])  # one transform gives keypoints and outline


def _unit_turn(angle: float) -> float:
    """``angle`` in [0, 2 pi) like the standard state (``%`` alone returns 2 pi for tiny negative angles)."""
    a = angle % (2 * np.pi)
    return 0.0 if a >= 2 * np.pi else a


class PushTEnv(gym.Env):
    """Push a T-shaped block onto a goal pose with a circular agent driven by absolute target positions.

    Observation (a dict): ``keypoints`` [25, 2] (block T, goal T, agent; order in
    :mod:`kpflow.tasks.pusht.geometry`), ``agent_pos`` [2], ``block_pose`` [3] and ``goal_pose`` [3] as
    ``(x, y, theta)`` with theta in [0, 2 pi) like the standard state. Action: the agent's absolute target [2],
    clipped to the workspace. Reward ``clip(coverage / threshold, 0, 1)`` as in the standard env; ``terminated``
    when coverage >= ``success_threshold``; ``truncated`` after ``max_steps`` steps (never when ``None``).
    ``info`` carries ``is_success``, ``coverage``, ``block_pose`` and ``n_steps``.

    ``reset(seed=s)`` draws a configuration of ``split`` (see :mod:`.splits`); ``options={"config": Config}`` or
    ``options={"state": [ax, ay, bx, by, theta]}`` (plus optional ``"goal_pose"``) resets to a given one.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        split: str = "in_distribution",
        goal: str = "random",
        success_threshold: float = 0.95,
        max_steps: int | None = None,
        physically_correct: bool = False,
        render_size: int = 512,
        render_keypoints: bool = False,
        render_mode: str | None = "rgb_array",
    ):
        if split not in SPLITS:
            raise ValueError(f"unknown Push-T split {split!r}; choose one of {SPLITS}")
        if goal not in GOAL_MODES:
            raise ValueError(f"unknown goal mode {goal!r}; choose one of {GOAL_MODES}")
        if not 0.0 < success_threshold <= 1.0:
            raise ValueError(f"success_threshold must be in (0, 1], got {success_threshold}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be 'rgb_array' or None, got {render_mode!r}")
        self.split, self.goal_mode = split, goal
        self.success_threshold = float(success_threshold)
        self.max_steps = max_steps
        self.physically_correct = physically_correct
        self.render_size, self.render_keypoints, self.render_mode = render_size, render_keypoints, render_mode
        self._build(get_workspace("standard" if split == "in_distribution" else "large"))
        self.goal_pose = np.array(FIXED_GOAL)
        self.n_steps: int | None = None  # None until the first reset
        self._last_target = None

    def _build(self, workspace) -> None:
        """Physics and spaces for ``workspace`` (a reset to a configuration of another workspace rebuilds them)."""
        self.workspace = workspace
        self.physics = PushTPhysics(workspace, self.physically_correct)
        s = float(workspace.size)
        pose = spaces.Box(np.array([-s, -s, 0.0]), np.array([2 * s, 2 * s, 2 * np.pi]), dtype=np.float64)
        self.action_space = spaces.Box(0.0, s, shape=(2,), dtype=np.float64)
        self.observation_space = spaces.Dict(
            {
                "keypoints": spaces.Box(-s, 2 * s, shape=(N_KEYPOINTS, 2), dtype=np.float64),
                "agent_pos": spaces.Box(-s, 2 * s, shape=(2,), dtype=np.float64),
                "block_pose": pose,
                "goal_pose": pose,
            }
        )

    # ------------------------------------------------------------------------------------------------ reset
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        if "config" in options:
            config = options["config"]
        elif "state" in options:
            state = np.asarray(options["state"], float)
            if state.shape != (5,) or not np.isfinite(state).all():
                raise ValueError(f"state must be 5 finite numbers (agent x, y, block x, y, angle), got {state}")
            goal = options.get("goal_pose", FIXED_GOAL)
            config = Config(tuple(state[:2]), tuple(state[2:]), tuple(np.asarray(goal, float)), self.workspace.name)
        else:
            config = sample_config(self.split, self.np_random, self.goal_mode)
        if not isinstance(config, Config):
            raise ValueError(f"options['config'] must be a kpflow Config, got {type(config).__name__}")
        if config.workspace != self.workspace.name:
            self._build(get_workspace(config.workspace))
        self.config = config
        self.goal_pose = np.array(config.goal_pose, float)
        self._goal_keypoints = t_keypoints(self.goal_pose)
        self._goal_polygon = t_polygon(self.goal_pose)
        self.physics.set_state(config.agent_pos, config.block_pose)
        self.physics.space.step(DT)  # the standard env runs one physics step after setting a state
        self.n_steps = 0
        self._last_target = None
        return self._observe()

    # ------------------------------------------------------------------------------------------------ step
    def step(self, action):
        if self.n_steps is None:
            raise RuntimeError("call reset() before step()")
        target = np.asarray(action, dtype=np.float64).reshape(-1)
        if target.shape != (2,) or not np.isfinite(target).all():
            raise ValueError(f"action must be 2 finite numbers (absolute target x, y), got {action!r}")
        target = np.clip(target, 0.0, self.workspace.size)
        self.physics.step(target)
        self.n_steps += 1
        self._last_target = target
        obs, info = self._observe()
        reward = float(np.clip(info["coverage"] / self.success_threshold, 0.0, 1.0))
        terminated = bool(info["is_success"])
        truncated = self.max_steps is not None and self.n_steps >= self.max_steps and not terminated
        return obs, reward, terminated, truncated, info

    def _observe(self):
        agent = self.physics.agent_pos
        pose = self.physics.block_pose
        points = to_world(pose, _BODY_POINTS)
        cov = outline_coverage(points[len(T_KEYPOINTS) :], self._goal_polygon)
        pose[2] = _unit_turn(pose[2])
        goal = self.goal_pose.copy()
        goal[2] = _unit_turn(goal[2])
        obs = {
            "keypoints": np.concatenate([points[: len(T_KEYPOINTS)], self._goal_keypoints, agent[None]]),
            "agent_pos": agent,
            "block_pose": pose,
            "goal_pose": goal,
        }
        info = {"coverage": cov, "is_success": cov >= self.success_threshold, "block_pose": pose, "n_steps": self.n_steps}
        return obs, info

    # ------------------------------------------------------------------------------------------------ render
    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        physics = self.physics
        keypoints = None
        if self.render_keypoints:
            keypoints = np.concatenate(
                [t_keypoints(physics.block_pose), self._goal_keypoints, physics.agent_pos[None]]
            )
        return render_scene(
            self.workspace,
            physics.block_pose,
            self.goal_pose,
            physics.agent_pos,
            self.render_size,
            keypoints=keypoints,
            target=self._last_target,
        )
