"""Push-T demonstrations on disk: expert ones collected on first use (``data=pusht_expert``), or any existing store
(``data=pusht_human``, a store grown by corrections), read with their goals as recorded or in hindsight
(:mod:`kpflow.data.hindsight`: the block's last keypoints as the goal's)."""

from __future__ import annotations

import os
from pathlib import Path

from kpflow.data.chunks import ChunkDataModule, raw_replay_help
from kpflow.data.episode_store import EpisodeStore
from kpflow.data.hindsight import GOALS, HindsightGoals
from kpflow.tasks.pusht.collection import check_collection, collect_pusht, collection_attrs
from kpflow.tasks.pusht.geometry import PUSHT_BLOCK, PUSHT_GOAL

#: Push-T's goal keypoints (12..23) are where the block's (0..11) belong, in the same order.
PUSHT_HINDSIGHT = HindsightGoals(object=PUSHT_BLOCK, goal=PUSHT_GOAL)


def pusht_hindsight(goals: str) -> HindsightGoals | None:
    """How Push-T demonstrations' goals are read: ``"recorded"`` (None) or ``"hindsight"`` (:data:`PUSHT_HINDSIGHT`)."""
    if goals not in GOALS:
        raise ValueError(f"goals must be one of {GOALS}; got {goals!r}")
    return PUSHT_HINDSIGHT if goals == "hindsight" else None


def ensure_pusht_demos(
    path: str | os.PathLike,
    n_episodes: int | None = 200,
    seed: int = 0,
    workers: int = 2,
    split: str = "in_distribution",
    goal: str = "random",
    max_steps: int = 600,
) -> EpisodeStore:
    """The expert store at ``path``, collected first when it does not exist yet or holds fewer episodes
    (an interrupted collection is continued where it stopped; see :func:`collect_pusht`).

    An existing store is used only if it is a collection of ``n_episodes`` episodes with the same split, goal and
    seed (and max_steps); otherwise a clear error says what differs (collect into another path). With
    ``n_episodes=None`` the store at ``path`` is taken as it is (one grown by corrections, or the imported human
    dataset) and must exist. Returns the store, open read-only.
    """
    path = Path(path)
    if n_episodes is None:
        if not (path / "meta" / "episode_ends").exists():
            raise FileNotFoundError(
                f"no episode store at {path}: with n_episodes=null the store must exist (collect it with "
                "kpflow-collect, or import the human dataset with python -m kpflow.tasks.pusht.replay_import SRC DEST)"
            )
        if raw := raw_replay_help(path, "keypoints"):  # refused before the store is read (and asked to be sealed)
            raise ValueError(raw)
        return EpisodeStore(path)
    want = collection_attrs(n_episodes, split, goal, seed, max_steps, False)
    if not (path / "meta" / "episode_ends").exists() or len(EpisodeStore(path)) < n_episodes:
        collect_pusht(path, n_episodes, split=split, goal=goal, seed=seed, max_steps=max_steps, workers=workers)
    store = EpisodeStore(path)
    check_collection(store, want)
    return store


def pusht_datamodule(
    path: str,
    n_episodes: int | None = 200,
    seed: int = 0,
    workers: int = 2,
    horizon: int = 20,
    batch_size: int = 256,
    val_fraction: float = 0.1,
    n_obs: int = 1,
    goals: str = "recorded",
    relabel_fragments: bool = False,
    max_episodes: int | None = None,
) -> ChunkDataModule:
    """Chunks (keypoints -> next ``horizon`` actions) of the Push-T store at ``path`` (see :func:`ensure_pusht_demos`:
    expert demonstrations collected if missing, or with ``n_episodes=None`` whatever store is there), the goals read
    as ``goals`` says (:func:`pusht_hindsight`); with ``goals="hindsight"``, ``relabel_fragments`` relabels the
    correction takeovers too (:mod:`kpflow.data.hindsight`; a source index always does). ``max_episodes``: train on
    (and, for policy transportation, index) only the store's first ``max_episodes`` episodes, as Diffusion Policy's
    configs do with ``max_train_episodes: 90``."""
    hindsight = pusht_hindsight(goals)  # a bad name is refused before anything is collected
    ensure_pusht_demos(path, n_episodes, seed, workers)
    return ChunkDataModule(
        path,
        horizon=horizon,
        batch_size=batch_size,
        val_fraction=val_fraction,
        seed=seed,
        n_obs=n_obs,
        hindsight=hindsight,
        relabel_fragments=relabel_fragments,
        max_episodes=max_episodes,
    )
