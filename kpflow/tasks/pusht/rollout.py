"""A Push-T episode: the one closed loop (:func:`kpflow.core.rollout.rollout`) from a configuration, with Push-T's
coverage read along the way. Evaluation runs it as it is, corrections give it an
:class:`~kpflow.core.rollout.Override` (the expert taking over), and keyboard teleoperation is a policy that may end
the episode (:class:`~kpflow.core.rollout.StopEpisode`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kpflow.core.rollout import Episode, Override, rollout

from .env import PushTEnv
from .scene import Config

#: Per-step fields of a recorded episode: the observation before each action, and that action.
RECORDED_FIELDS = ("keypoints", "agent_pos", "block_pose", "goal_pose")


def coverage_summary(episode: Episode, thresholds) -> tuple[dict, float, float]:
    """An episode's coverage (its ``tracked["coverage"]`` after each step): threshold -> the first step (1-based)
    reaching it (None: never), the final coverage and the largest, the start's included."""
    coverage = np.asarray(episode.tracked["coverage"])
    first = {th: int(np.flatnonzero(coverage >= th)[0]) + 1 if (coverage >= th).any() else None for th in thresholds}
    return first, float(episode.info["coverage"]), float(max([episode.first_info["coverage"], *coverage.tolist()]))


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

    ``policy`` has ``reset(seed)`` and ``act(obs)`` returning one target ``[2]`` or a chunk ``[H, 2]``. The episode
    ends on ``env``'s success (its ``success_threshold``); ``first_step`` also records when lower ``thresholds`` were
    first reached. With an ``override`` (the expert's corrections), ``overridden`` marks the steps it took. A policy
    may end the episode early by raising :class:`~kpflow.core.rollout.StopEpisode` (``steps`` then counts the steps
    taken).
    """
    if render and env.render_mode != "rgb_array":
        raise ValueError(f"render=True needs an env made with render_mode='rgb_array', not {env.render_mode!r}")
    episode = rollout(env, policy, max_steps, seed, {"options": {"config": config}}, RECORDED_FIELDS if record else (), render, override,
                      ("coverage",))  # fmt: skip
    first, final, best = coverage_summary(episode, thresholds)
    return EpisodeResult(
        success=episode.success,
        coverage=final,
        max_coverage=best,
        steps=episode.steps,
        seconds=episode.seconds,
        first_step=first,
        episode=episode.records if record else None,
        frames=episode.frames,
        overridden=episode.overridden,
    )
