"""Collecting demonstrations into an :class:`EpisodeStore`, in parallel, with a progress bar: the scripted expert's,
or a policy's own successful episodes (self-generated demonstrations: no one demonstrates more, the simulator
checks each episode and only the successes are kept)."""

from __future__ import annotations

import multiprocessing as mp
import os
import sys
from itertools import count
from pathlib import Path

from tqdm import tqdm

from kpflow.data.episode_store import EpisodeStore
from kpflow.tasks.pusht.env import PushTEnv
from kpflow.tasks.pusht.rollout import EpisodeResult, run_episode
from kpflow.tasks.pusht.scene import GOAL_MODES, SPLITS, split_config
from kpflow.tasks.pusht.task import PushTTask
from kpflow.utils.config_checks import Key
from kpflow.utils.video import write_video


def collect_episode(
    policy,
    split: str,
    index: int,
    seed: int,
    goal: str,
    max_steps: int,
    success_threshold: float = 0.95,
    render: bool = False,
) -> tuple[int, EpisodeResult]:
    """Roll out ``policy`` (``reset``/``act``; None: the scripted expert planned for the configuration) on
    configuration ``index`` of ``split`` (``standard``: Diffusion Policy's start state for seed ``index``), reseeded by
    ``seed`` and ``index``, and record it."""
    config = (
        PushTTask().sample_scene(split, index, seed) if split == "standard" else split_config(split, index, seed, goal)
    )
    env = PushTEnv(
        split=split,
        goal=goal,
        success_threshold=success_threshold,
        render_size=256,
        render_mode="rgb_array" if render else None,
    )
    actor = PushTTask().demonstrator(config) if policy is None else policy
    result = run_episode(env, actor, config, max_steps, seed=seed * 100_003 + index, record=True, render=render)
    return index, result


#: the policy a collection rolls out instead of the expert (set before the worker processes fork, so they share it)
_POLICY = None


def _job(args) -> tuple[int, EpisodeResult]:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    return collect_episode(_POLICY, *args)


def collection_attrs(
    n_episodes: int, split: str, goal: str, seed: int, max_steps: int, keep_failures: bool, source: str = "expert"
) -> dict:
    """The store attrs that identify a collection (including how many episodes it is meant to hold): a store is
    continued only by a collection with the same ones."""
    return {
        "task": "pusht",
        "source": source,
        "n_episodes": n_episodes,
        "split": split,
        "goal": goal,
        "seed": seed,
        "max_steps": max_steps,
        "keep_failures": keep_failures,
    }


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
    policy=None,
    source: str = "expert",
    first_index: int = 0,
) -> dict:
    """Collect ``n_episodes`` expert demonstrations of Push-T into the store at ``store_path``; with ``policy``, that
    policy's own episodes instead (``source`` names it in the store's attrs, e.g. ``"policy:transport"``), and with
    ``split="standard"`` on Diffusion Policy's start states (config index = its env seed).

    Configurations are taken in order (``first_index``, +1, +2, ... of the seeded ``split``); failed episodes are skipped unless
    ``keep_failures``, so the store holds exactly ``n_episodes``. Episodes are committed one by one in index order
    whatever the number of ``workers``, so the same arguments give the same store. That also makes an interrupted
    collection resumable: a store that holds fewer episodes of the same collection (same split, goal, seed,
    max_steps, keep_failures) is continued after its last committed configuration, and ends up identical to an
    uninterrupted one. Another collection's store (one meant for another number of episodes too), or one with more
    episodes, is refused before anything is written. A second process collecting into the same store waits for the first (the store's write lock) and then
    finds it complete. The first ``videos`` kept episodes are also written as mp4 to ``video_dir``.

    Returns a summary (episodes, resumed_from, attempts, successes, steps of the episodes collected now, paths).
    """
    for name, value, lo in (
        ("n_episodes", n_episodes, 1),
        ("workers", workers, 1),
        ("max_steps", max_steps, 1),
        ("videos", videos, 0),
        ("seed", seed, 0),
    ):
        Key(int, lo=lo).check(name, value)
    n_episodes, workers, max_steps, videos, seed = map(
        int, (n_episodes, workers, max_steps, videos, seed)
    )  # plain ints for the attrs
    Key(int, lo=0).check("first_index", first_index)
    splits = (*SPLITS, "standard") if policy is not None else SPLITS  # the expert plans for Table 1's workspaces only
    if split not in splits:
        raise ValueError(
            f"unknown Push-T split {split!r} for {'a policy' if policy is not None else 'the expert'}; choose one of {splits}"
        )
    if goal not in GOAL_MODES:
        raise ValueError(f"unknown goal mode {goal!r}; choose one of {GOAL_MODES}")
    if (policy is None) != (source == "expert"):
        raise ValueError(
            f"source names who acts: 'expert' without a policy, another name with one; got source={source!r} and policy={policy!r}"
        )
    want = collection_attrs(n_episodes, split, goal, seed, max_steps, bool(keep_failures), source)
    if (Path(store_path) / "meta" / "episode_ends").exists():
        check_collection(EpisodeStore(store_path), want)  # before the write lock repairs anything
    with EpisodeStore(store_path, mode="a", wait=None) as store:
        have = len(store)
        check_collection(store, want)
        if not have:
            store.attrs.update(want)
        start = store.episode_attrs(have - 1)["config_index"] + 1 if have else int(first_index)
        global _POLICY
        _POLICY = policy
        try:
            return _collect(store, n_episodes, have, start, want, workers, videos, video_dir, progress)
        finally:
            _POLICY = None


def check_collection(store: EpisodeStore, want: dict) -> None:
    """Raise ``ValueError`` unless ``store`` is empty or a (partial) collection with the attrs ``want`` (see
    :func:`collection_attrs`) holding at most ``want["n_episodes"]`` episodes."""
    if not len(store) and not store.attrs.get("task"):
        return
    attrs = store.attrs.asdict()
    optional = ("n_episodes", "max_steps", "keep_failures")  # absent from stores collected before they were recorded
    differ = {
        k: (attrs.get(k), v) for k, v in want.items() if attrs.get(k) != v and not (k in optional and k not in attrs)
    }
    if differ:
        raise ValueError(
            f"{store.path} holds {len(store)} episodes of another collection ({', '.join(f'{k}: {a!r} there, {b!r} asked' for k, (a, b) in differ.items())}); "
            "collect into another path"
        )
    if len(store) > want["n_episodes"]:
        raise ValueError(
            f"{store.path} already holds {len(store)} episodes, more than the {want['n_episodes']} asked for"
        )
    if len(store) and "config_index" not in store.episode_attrs(len(store) - 1):
        raise ValueError(f"{store.path}: its last episode has no config_index, so the collection cannot be continued")


def _collect(store, n_episodes, have, start, want, workers, videos, video_dir, progress) -> dict:
    split, goal, seed, max_steps = want["split"], want["goal"], want["seed"], want["max_steps"]
    video_dir = Path(video_dir) if video_dir is not None else store.path.parent
    jobs = ((split, i, seed, goal, max_steps, 0.95, have + (i - start) < videos) for i in count(start))
    kept, attempts, successes, steps, video_paths = have, 0, 0, [], []
    pool = mp.get_context("fork").Pool(workers) if workers > 1 and kept < n_episodes else None
    results = pool.imap(_job, jobs) if pool is not None else map(_job, jobs)
    if progress and kept < n_episodes:
        print(f"collecting {n_episodes - kept} Push-T episodes into {store.path}", file=sys.stderr, flush=True)
    bar = tqdm(
        total=n_episodes,
        initial=have,
        desc=f"collect pusht/{split} ({want['source']})",
        unit="ep",
        disable=not progress,
    )
    try:
        while kept < n_episodes:
            index, result = next(results)
            attempts += 1
            successes += result.success
            if not (result.success or want["keep_failures"]):
                continue
            attrs = {
                "config_index": index,
                "success": result.success,
                "coverage": result.coverage,
                "steps": result.steps,
            }
            store.add_episode(result.episode, attrs=attrs)
            steps.append(result.steps)
            if result.frames is not None and kept < videos:
                video_paths.append(str(write_video(result.frames, video_dir / f"episode_{kept:03d}.mp4")))
            kept += 1
            bar.update(1)
            bar.set_postfix(success=f"{successes}/{attempts}")
    finally:
        bar.close()
        if pool is not None:
            pool.terminate()
    return {
        "store": str(store.path),
        "episodes": kept,
        "resumed_from": have,
        "attempts": attempts,
        "successes": successes,
        "steps": int(sum(steps)),
        "videos": video_paths,
    }
