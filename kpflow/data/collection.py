"""Collecting scripted-expert demonstrations into an :class:`EpisodeStore`, in parallel, with a progress bar."""

from __future__ import annotations

import multiprocessing as mp
import os
from itertools import count
from pathlib import Path

from tqdm import tqdm

from ..tasks.pusht.env import PushTEnv
from ..tasks.pusht.expert import PushTExpert
from ..utils.video import write_video
from ..tasks.pusht.rollout import EpisodeResult, run_episode
from ..tasks.pusht.splits import split_config
from .episode_store import EpisodeStore


def expert_episode(
    split: str, index: int, seed: int, goal: str, max_steps: int, success_threshold: float = 0.95, render: bool = False
) -> tuple[int, EpisodeResult]:
    """Roll out the expert on configuration ``index`` of ``split`` (expert seeded by ``seed`` and ``index``)."""
    config = split_config(split, index, seed, goal)
    env = PushTEnv(split=split, goal=goal, success_threshold=success_threshold, render_size=256)
    expert = PushTExpert(config.workspace)
    result = run_episode(env, expert, config, max_steps, seed=seed * 100_003 + index, record=True, render=render)
    return index, result


def _job(args) -> tuple[int, EpisodeResult]:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    return expert_episode(*args)


def collect_pusht(
    store_path: str | os.PathLike,
    n_episodes: int,
    split: str = "in_distribution",
    goal: str = "random",
    seed: int = 0,
    max_steps: int = 600,
    workers: int = 1,
    keep_failures: bool = False,
    videos: int = 0,
    video_dir: str | os.PathLike | None = None,
    progress: bool = True,
) -> dict:
    """Collect ``n_episodes`` expert demonstrations of Push-T into the store at ``store_path``.

    Configurations are taken in order (0, 1, 2, ... of the seeded ``split``); failed episodes are skipped unless
    ``keep_failures``, so the store holds exactly ``n_episodes``. Episodes are committed one by one in index order
    whatever the number of ``workers``, so the same arguments give the same store. The first ``videos`` kept
    episodes are also written as mp4 to ``video_dir``. Returns a summary (attempts, successes, steps, paths).
    """
    if n_episodes < 1:
        raise ValueError(f"n_episodes must be >= 1, got {n_episodes}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    store = EpisodeStore(store_path, mode="a")
    if len(store):
        raise ValueError(f"{store_path} already holds {len(store)} episodes; collect into a new path")
    store.attrs.update({"task": "pusht", "split": split, "goal": goal, "seed": seed, "source": "expert"})
    video_dir = Path(video_dir) if video_dir is not None else Path(store_path).parent
    jobs = ((split, i, seed, goal, max_steps, 0.95, i < videos) for i in count())
    kept, attempts, successes, steps, video_paths = 0, 0, 0, [], []
    pool = mp.get_context("fork").Pool(workers) if workers > 1 else None
    results = pool.imap(_job, jobs) if pool is not None else map(_job, jobs)
    bar = tqdm(total=n_episodes, desc=f"collect pusht/{split}", unit="ep", disable=not progress)
    try:
        for index, result in results:
            attempts += 1
            successes += result.success
            if not (result.success or keep_failures):
                continue
            attrs = {"config_index": index, "success": result.success, "coverage": result.coverage, "steps": result.steps}
            store.add_episode(result.episode, attrs=attrs)
            steps.append(result.steps)
            if result.frames is not None and len(video_paths) < videos:
                video_paths.append(str(write_video(result.frames, video_dir / f"episode_{kept:03d}.mp4")))
            kept += 1
            bar.update(1)
            bar.set_postfix(success=f"{successes}/{attempts}")
            if kept == n_episodes:
                break
    finally:
        bar.close()
        if pool is not None:
            pool.terminate()
    return {
        "store": str(store_path),
        "episodes": kept,
        "attempts": attempts,
        "successes": successes,
        "steps": int(sum(steps)),
        "videos": video_paths,
    }
