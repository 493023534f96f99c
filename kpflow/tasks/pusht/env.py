"""The Push-T environment: standard physics, 25 keypoints, Gymnasium API."""

from __future__ import annotations

from collections.abc import Mapping

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from .geometry import N_KEYPOINTS, OUTLINE, T_KEYPOINTS, outline_coverage, t_keypoints, t_polygon, to_world
from .physics import DT, PushTPhysics
from .render import render_scene
from .scene import FIXED_GOAL, GOAL_MODES, SPLITS, Config, sample_config, split_workspace, standard_config
from .workspace import get_workspace

_BODY_POINTS = np.concatenate([T_KEYPOINTS, OUTLINE])  # one transform gives keypoints and outline
#: the env's splits: Table 1's three and Diffusion Policy's protocol
ENV_SPLITS = (*SPLITS, "standard")
#: the keys ``reset(options=...)`` understands
RESET_OPTIONS = ("config", "state", "goal_pose")


def _checked(value, name: str, what: str, labels: tuple[str, ...], workspace) -> np.ndarray:
    """``value`` as ``len(labels)`` finite floats whose positions (the labels not named "angle") lie in the
    arena ``[0, workspace.size]``; otherwise a ``ValueError`` naming ``name``, the entry and the bounds."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != (len(labels),) or not np.isfinite(arr).all():
        raise ValueError(f"{name} must be {what}, got {value!r}")
    for i, label in enumerate(labels):
        if label != "angle" and not 0.0 <= arr[i] <= workspace.size:
            raise ValueError(
                f"{name}[{i}] ({label}) = {arr[i]:g} is outside the {workspace.name} arena: positions must lie in "
                f"[0, {workspace.size}]"
            )
    return arr


_STATE = (
    "state",
    "5 finite numbers (agent x, y, block x, y, angle)",
    ("agent x", "agent y", "block x", "block y", "angle"),
)
_GOAL = ("goal_pose", "3 finite numbers (goal x, y, angle)", ("goal x", "goal y", "angle"))


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

    ``split`` fixes the workspace, and with it the spaces, for the instance's lifetime: the 512-px arena for
    ``in_distribution`` and ``standard``, the 1024-px one for ``robot_ood`` and ``object_ood``. ``reset(seed=s)``
    draws a configuration of ``split`` (see :mod:`.scene`); with ``split="standard"`` it is Diffusion Policy's start
    state for seed ``s`` (:func:`~.scene.standard_config`). ``options={"config": Config}`` (of the instance's
    workspace) or ``options={"state": [ax, ay, bx, by, theta]}`` (plus optional ``"goal_pose"`` ``(x, y, theta)``,
    default :data:`~.scene.FIXED_GOAL`) resets to a given one. Positions must lie in the arena ``[0, size]`` and
    every entry must be finite; a bad value, an unknown option key, a config of another workspace, or a combination
    that would ignore one (``config`` with ``state`` or ``goal_pose``) raises ``ValueError``.

    Registered ids (``gymnasium.make``, after ``import kpflow``): ``kpflow/PushT-v0`` (Diffusion Policy's protocol:
    ``split="standard"``, fixed goal, 300 steps), ``kpflow/PushT-InDistribution-v0``, ``kpflow/PushT-RobotOOD-v0``
    and ``kpflow/PushT-ObjectOOD-v0`` (random goals, 1200 steps, Table 1's splits).
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
        render_mode: str | None = None,
    ):
        if split not in ENV_SPLITS:
            raise ValueError(f"unknown Push-T split {split!r}; choose one of {ENV_SPLITS}")
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
        self._build(get_workspace(split_workspace(split)))
        self.goal_pose = np.array(FIXED_GOAL)
        self.n_steps: int | None = None  # None until the first reset
        self._last_target = None

    def _build(self, workspace) -> None:
        """Physics and spaces for ``workspace``, once per instance."""
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
        options = {} if options is None else options
        if not isinstance(options, Mapping):
            raise ValueError(f"options must be a dict with keys among {RESET_OPTIONS}, got {type(options).__name__}")
        unknown = sorted(str(k) for k in options if k not in RESET_OPTIONS)
        if unknown:
            raise ValueError(f"unknown reset option(s) {unknown}; known options are {list(RESET_OPTIONS)}")
        if "config" in options and ("state" in options or "goal_pose" in options):
            given = [k for k in ("state", "goal_pose") if k in options]
            raise ValueError(f"options['config'] already sets the whole configuration: drop {given} or the config")
        if "goal_pose" in options and "state" not in options:
            raise ValueError("options['goal_pose'] applies only together with options['state']")
        if "config" in options:
            config = options["config"]
            if not isinstance(config, Config):
                raise ValueError(f"options['config'] must be a kpflow Config, got {type(config).__name__}")
            if config.workspace != self.workspace.name:
                raise ValueError(
                    f"options['config'] is a configuration of the {config.workspace} workspace but this env's is"
                    f" {self.workspace.name} (fixed by split={self.split!r}): make the env with a split of that workspace"
                )
            ws = self.workspace
            pose = "3 finite numbers (x, y, angle)"
            _checked(config.agent_pos, "config.agent_pos", "2 finite numbers (x, y)", ("agent x", "agent y"), ws)
            _checked(config.block_pose, "config.block_pose", pose, ("block x", "block y", "angle"), ws)
            _checked(config.goal_pose, "config.goal_pose", pose, ("goal x", "goal y", "angle"), ws)
        elif "state" in options:
            state = _checked(options["state"], *_STATE, self.workspace)
            goal = _checked(options.get("goal_pose", FIXED_GOAL), *_GOAL, self.workspace)
            config = Config(tuple(state[:2]), tuple(state[2:]), tuple(goal), self.workspace.name)
        elif self.split == "standard":
            config = standard_config(int(self.np_random.integers(2**32)) if seed is None else int(seed))
        else:
            config = sample_config(self.split, self.np_random, self.goal_mode)
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
        info = {
            "coverage": cov,
            "is_success": cov >= self.success_threshold,
            "block_pose": pose,
            "n_steps": self.n_steps,
        }
        return obs, info

    # ------------------------------------------------------------------------------------------------ render
    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        physics = self.physics
        keypoints = None
        if self.render_keypoints:
            keypoints = np.concatenate([t_keypoints(physics.block_pose), self._goal_keypoints, physics.agent_pos[None]])
        return render_scene(
            self.workspace,
            physics.block_pose,
            self.goal_pose,
            physics.agent_pos,
            self.render_size,
            keypoints=keypoints,
            target=self._last_target,
        )
