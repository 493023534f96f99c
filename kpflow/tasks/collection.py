"""Collecting a Gymnasium task's expert episodes into a demonstration store.

:func:`collect_gym_episodes` rolls the task's scripted expert out (:func:`~kpflow.core.rollout.rollout`, the one
closed loop) on scenes ``seed, seed + 1, ...`` and commits its successful episodes to an
:class:`~kpflow.data.episode_store.EpisodeStore` as ``keypoints [T, K, D]`` (observed before each step) and
``action [T, A]`` (Diffusion Policy's convention).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from kpflow.core.rollout import rollout
from kpflow.core.task import GymTask
from kpflow.data.episode_store import EpisodeStore


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
    with (
        EpisodeStore(store_path, mode="a") as store,
        tqdm(total=n_episodes, desc=f"collect {task.name}", disable=not progress) as bar,
    ):
        store.attrs.update({"task": task.name, "condition": condition})
        while stored < n_episodes:
            if attempts >= 10 * n_episodes:
                raise RuntimeError(
                    f"{task.name}'s expert succeeded {successes} times in {attempts} attempts: check the task"
                )
            scene = seed + attempts
            episode = rollout(
                env,
                expert,
                task.max_steps,
                scene,
                {"seed": scene},
                ("keypoints",),
                action_dim=int(np.prod(env.action_space.shape)),
            )
            attempts, successes = attempts + 1, successes + episode.success
            if episode.success or keep_failures:
                store.add_episode(episode.records)
                stored, steps = stored + 1, steps + episode.steps
                bar.update()
    env.close()
    return {"store": str(store_path), "episodes": stored, "attempts": attempts, "successes": successes, "steps": steps}
