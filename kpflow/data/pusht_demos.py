"""Push-T demonstrations on disk: expert ones collected on first use (``data=pusht_expert``), or any existing store
(``data=pusht_human``, a store grown by corrections)."""

from __future__ import annotations

import os
from pathlib import Path

from .chunks import ChunkDataModule
from .collection import check_collection, collect_pusht, collection_attrs
from .episode_store import EpisodeStore


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
                "python -m kpflow.collect, or import the human dataset with python -m kpflow.data.pusht_import SRC DEST)"
            )
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
) -> ChunkDataModule:
    """Chunks (keypoints -> next ``horizon`` actions) of the Push-T store at ``path`` (see :func:`ensure_pusht_demos`:
    expert demonstrations collected if missing, or with ``n_episodes=None`` whatever store is there)."""
    ensure_pusht_demos(path, n_episodes, seed, workers)
    return ChunkDataModule(path, horizon=horizon, batch_size=batch_size, val_fraction=val_fraction, seed=seed, n_obs=n_obs)
