"""The one Push-T episode loop: a policy acts (in open-loop chunks) until success or the step limit, the episode
recorded in the Diffusion Policy convention. Evaluation runs it as it is, corrections give it an :class:`Override`
(the expert taking over), and keyboard teleoperation is a policy that may end the episode (:class:`StopEpisode`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from kpflow.policies.base import ClosedLoop

from .env import PushTEnv
from .scene import Config

#: Per-step fields of a recorded episode: the observation before each action, and that action.
RECORDED_FIELDS = ("keypoints", "agent_pos", "block_pose", "goal_pose")


@dataclass
class EpisodeResult:
    """Outcome of one episode. ``first_step`` maps a coverage threshold to the first step reaching it (or None)."""

    success: bool
    coverage: float
    max_coverage: float
    steps: int
    seconds: float
    first_step: dict = field(default_factory=dict)
    episode: dict | None = None  # recorded arrays [T, ...] (float32) when ``record``
    frames: list | None = None  # RGB frames when ``render``
    overridden: np.ndarray | None = None  # [T] bool: the steps an override took (when one was given)


class StopEpisode(Exception):
    """Raised by a policy's ``act`` to end the episode before its next step (a person pressing Enter)."""


class Override(Protocol):
    """Something that may take control from the policy for a while (an expert correcting it): each step it is asked
    first, and an action it returns replaces the policy's (whose pending chunk is then dropped)."""

    def start(self, env: PushTEnv, obs: dict, info: dict, seed: int | None) -> None:
        """A new episode began in ``env`` with ``obs`` and ``info``."""

    def act(self, step: int, obs: dict) -> np.ndarray | None:
        """The action for ``step``, or None to leave it to the policy."""

    def update(self, step: int, info: dict) -> None:
        """``step`` was taken; ``info`` is the env's after it."""


def _next_action(loop: ClosedLoop, override: Override | None, step: int, obs: dict) -> tuple[np.ndarray, bool]:
    """The override's action if it takes this step (the policy's pending chunk is then dropped: it starts afresh
    when it gets control back), else the policy's; and whether the override took it."""
    action = None if override is None else override.act(step, obs)
    if action is None:
        return loop.action(obs), False
    loop.drop()
    return np.asarray(action, dtype=np.float64), True


def run_episode(
    env: PushTEnv,
    policy,
    config: Config,
    max_steps: int,
    seed: int | None = None,
    thresholds: tuple[float, ...] = (0.85, 0.95),
    record: bool = False,
    render: bool = False,
    override: Override | None = None,
) -> EpisodeResult:
    """Reset ``env`` to ``config`` and run ``policy`` until success or ``max_steps`` steps.

    ``policy`` has ``reset(seed)`` and ``act(obs)`` returning one target ``[2]`` or a chunk ``[H, 2]``, run through
    :class:`~kpflow.policies.base.ClosedLoop` (the observation history and the action queue). The episode ends
    on ``env``'s success (its ``success_threshold``); ``first_step`` also records when lower ``thresholds`` were
    first reached. With an ``override`` (:class:`Override`: the expert's corrections), ``overridden`` marks the
    steps it took. A policy may end the episode early by raising :class:`StopEpisode` (``steps`` then counts the
    steps taken).
    """
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    if render and env.render_mode != "rgb_array":
        raise ValueError(f"render=True needs an env made with render_mode='rgb_array', not {env.render_mode!r}")
    obs, info = env.reset(options={"config": config})
    loop = ClosedLoop(policy)
    loop.reset(seed)
    if override is not None:
        override.start(env, obs, info, seed)
    log = {k: [] for k in (*RECORDED_FIELDS, "action")} if record else None
    frames = [env.render()] if render else None
    first = {th: None for th in thresholds}
    best, terminated, overridden = info["coverage"], False, []
    start, steps = time.perf_counter(), 0
    for step in range(max_steps):
        loop.observe(obs)
        try:
            action, took_over = _next_action(loop, override, step, obs)
        except StopEpisode:
            break
        overridden.append(took_over)
        if log is not None:
            for k in RECORDED_FIELDS:
                log[k].append(obs[k])
            log["action"].append(action)
        obs, _, terminated, _, info = env.step(action)
        steps += 1
        if override is not None:
            override.update(step, info)
        if frames is not None:
            frames.append(env.render())
        best = max(best, info["coverage"])
        first.update({th: step + 1 for th in thresholds if first[th] is None and info["coverage"] >= th})
        if terminated:
            break
    episode = {k: np.asarray(v, dtype=np.float32) for k, v in log.items()} if log is not None else None
    return EpisodeResult(
        success=bool(terminated),
        coverage=float(info["coverage"]),
        max_coverage=float(best),
        steps=steps,
        seconds=time.perf_counter() - start,
        first_step=first,
        episode=episode,
        frames=frames,
        overridden=np.array(overridden, bool) if override is not None else None,
    )
