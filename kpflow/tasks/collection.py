"""Collecting a Gymnasium task's episodes into a demonstration store: the one path of ``kpflow-collect``.

:func:`collect_episodes` takes the task and a :class:`CollectRequest` (what to collect, named the same for every
task). A task with a collector of its own (a ``collect(store_path, request)`` method: Push-T's runs worker processes,
records videos, resumes a store and lets a trained policy act) is handed the request; any other
:class:`~kpflow.core.task.GymTask` gets :func:`collect_gym_episodes`, which rolls the task's scripted expert out
(:func:`~kpflow.core.rollout.rollout`, the one closed loop) on scenes ``seed, seed + 1, ...`` and commits its
successful episodes to an :class:`~kpflow.data.episode_store.EpisodeStore` as ``keypoints [T, K, D]`` (observed
before each step) and ``action [T, A]`` (Diffusion Policy's convention). An option that collector cannot honour is
refused by name.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from kpflow.core.rollout import rollout
from kpflow.core.task import GymTask
from kpflow.data.episode_store import EpisodeStore


@dataclass(frozen=True)
class CollectRequest:
    """What ``kpflow-collect`` asks of a task's collector. None: the collector's default.

    Attributes:
        n_episodes: episodes the store ends up holding.
        condition: the task's condition (None: its first).
        seed: the scenes' stream.
        keep_failures: store failed episodes too.
        first_index: the first scene index.
        max_steps: the longest episode (None: the collector's).
        workers: processes rolling episodes out (None: the collector's).
        videos: mp4s of the first episodes, written to ``video_dir``.
        policy: who acts instead of the expert (a built policy), named ``source`` in the store.
        options: the task's own options (Push-T: ``goal``).
    """

    n_episodes: int
    condition: str | None = None
    seed: int = 0
    keep_failures: bool = False
    first_index: int = 0
    max_steps: int | None = None
    workers: int | None = None
    videos: int | None = None
    video_dir: Path | None = None
    policy: Any = None
    source: str = "expert"
    options: Mapping[str, Any] = field(default_factory=dict)
    progress: bool = True


def check_collectable(task) -> None:
    """Raise ``ValueError`` naming ``task``'s type unless it is a :class:`~kpflow.core.task.GymTask`."""
    if not isinstance(task, GymTask):
        raise ValueError(
            f"kpflow-collect collects a Gymnasium task with an expert (kpflow.core.task.GymTask, e.g. Push-T), not {type(task).__name__}"
        )


def collect_episodes(task: GymTask, store_path: str | Path, request: CollectRequest) -> dict:
    """Collect ``request`` of ``task`` into the store at ``store_path`` (module docstring); returns the collector's
    summary (``store``, ``episodes``, ``attempts``, ``successes``, ``steps``, ...)."""
    check_collectable(task)
    own = getattr(task, "collect", None)
    if own is not None:
        return own(Path(store_path), request)
    unused = [name for name, value, default in (("policy", request.policy, None), ("first_index", request.first_index, 0),
              ("videos", request.videos or 0, 0), ("workers", request.workers or 1, 1)) if value != default]  # fmt: skip
    unused += [f"options.{k}" for k, v in request.options.items() if v is not None]
    if unused:
        raise ValueError(
            f"{task.name}'s collection (its expert, in one process, on scenes seed, seed + 1, ...) takes no "
            f"{', '.join(unused)}: drop {'it' if len(unused) == 1 else 'them'}"
        )
    return collect_gym_episodes(task, store_path, request.n_episodes, request.condition, request.seed,
                                request.keep_failures, request.progress, request.max_steps)  # fmt: skip


def collect_gym_episodes(task: GymTask, store_path: str | Path, n_episodes: int, condition: str | None = None, seed: int = 0,
                         keep_failures: bool = False, progress: bool = True, max_steps: int | None = None) -> dict:  # fmt: skip
    """Roll ``task``'s expert out on scenes ``seed, seed + 1, ...`` of ``condition`` (the task's first by default),
    at most ``max_steps`` each (None: ``task.max_steps``), until ``n_episodes`` are stored in the store at
    ``store_path`` (appended; successes only unless ``keep_failures``). Returns the counts. Raises ``ValueError``
    when the task has no expert."""
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
                task.max_steps if max_steps is None else int(max_steps),
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
