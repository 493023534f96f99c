"""One closed-loop episode of a :class:`~kpflow.tasks.base.GymTask`, and collecting a task's expert episodes.

:func:`run_gym_episode` resets the env to a seeded scene, runs the policy through
:class:`~kpflow.policies.base.ClosedLoop` (its observation history and action queue) one action per ``env.step``, and
records what a demonstration store holds: the keypoints observed before each step and the action taken (Diffusion
Policy's convention). The episode ends on ``info["is_success"]``, on ``terminated``/``truncated``, or after
``max_steps``. :func:`collect_gym_episodes` commits the expert's successful episodes to an
:class:`~kpflow.data.episode_store.EpisodeStore` as ``keypoints [T, K, D]`` and ``action [T, A]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from kpflow.data.episode_store import EpisodeStore
from kpflow.policies.base import ClosedLoop, Policy

from .base import GymTask


@dataclass(frozen=True)
class GymEpisode:
    """How an episode went: ``success``, the ``steps`` taken, the policy's ``decisions`` (chunks asked for), the
    ``keypoints [T, K, D]`` observed before each step and the ``actions [T, A]`` taken."""

    success: bool
    steps: int
    decisions: int
    keypoints: np.ndarray
    actions: np.ndarray


def run_gym_episode(env, policy: Policy, seed: int, max_steps: int, frames: list | None = None) -> GymEpisode:
    """Run ``policy`` in ``env`` from ``env.reset(seed=seed)`` (module docstring); ``frames`` collects ``env.render()``."""
    obs, _ = env.reset(seed=int(seed))
    loop = ClosedLoop(policy, int(np.prod(env.action_space.shape)))
    loop.reset(seed)
    keypoints, actions, success = [], [], False
    if frames is not None:
        frames.append(env.render())
    for _ in range(int(max_steps)):
        loop.observe(obs)
        action = loop.action(obs)
        keypoints.append(np.asarray(obs["keypoints"], np.float32))
        actions.append(np.asarray(action, np.float32))
        obs, _, terminated, truncated, info = env.step(action)
        if frames is not None:
            frames.append(env.render())
        if info.get("is_success", False):
            success = True
            break
        if terminated or truncated:
            break
    return GymEpisode(success, len(actions), loop.decisions, np.stack(keypoints), np.stack(actions))


def collect_gym_episodes(task: GymTask, store_path: str | Path, n_episodes: int, condition: str | None = None, seed: int = 0,
                         keep_failures: bool = False, progress: bool = True) -> dict:  # fmt: skip
    """Roll ``task``'s expert out on scenes ``seed, seed + 1, ...`` of ``condition`` (the task's first by default)
    until ``n_episodes`` are stored in the store at ``store_path`` (appended; successes only unless
    ``keep_failures``). Returns the counts. Raises ``ValueError`` when the task has no expert."""
    condition = condition or task.conditions[0]
    task.check_condition(condition)
    expert = task.expert()
    if expert is None:
        raise ValueError(f"{task.name} has no scripted expert (GymTask.expert): collect its demonstrations another way")
    env = task.make_env(condition)
    attempts = stored = successes = steps = 0
    with EpisodeStore(store_path, mode="a") as store, tqdm(total=n_episodes, desc=f"collect {task.name}", disable=not progress) as bar:
        store.attrs.update({"task": task.name, "condition": condition})
        while stored < n_episodes:
            if attempts >= 10 * n_episodes:
                raise RuntimeError(f"{task.name}'s expert succeeded {successes} times in {attempts} attempts: check the task")
            episode = run_gym_episode(env, expert, seed + attempts, task.max_steps)
            attempts, successes = attempts + 1, successes + episode.success
            if episode.success or keep_failures:
                store.add_episode({"keypoints": episode.keypoints, "action": episode.actions})
                stored, steps = stored + 1, steps + episode.steps
                bar.update()
    env.close()
    return {"store": str(store_path), "episodes": stored, "attempts": attempts, "successes": successes, "steps": steps}
