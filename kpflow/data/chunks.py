"""Action-chunk training data from an :class:`~kpflow.data.episode_store.EpisodeStore`: for each time step
the observation and the next ``H`` actions, split by episode into train and validation."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import lightning
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from kpflow.data.episode_store import EpisodeStore
from kpflow.data.hindsight import HindsightGoals, fragment_episodes
from kpflow.data.lerobot_dataset import KeypointMap, is_lerobot, naming_help, open_lerobot


@dataclass(frozen=True)
class TrainingChunks:
    """What a policy's processor is fitted to (:meth:`ChunkDataModule.training_chunks`): one row per step of the
    training episodes, the world ``keypoints [N, K, D]`` observed, the next ``horizon`` actions ``chunks [N, H, A]``
    (the episode's last repeated past its end) and ``mask [N, H]`` (true on real steps); ``n_obs``: the frames of
    history the data module hands the model with each."""

    keypoints: np.ndarray
    chunks: np.ndarray
    mask: np.ndarray
    horizon: int
    n_obs: int


class ChunkDataset(Dataset):
    """One item per time step ``t`` of each listed episode.

    Each item is a dict: ``obs`` (float32, the field's trailing shape, e.g. ``[25, 2]``), ``actions``
    (float32 ``[H, A]``: ``a[t : t + H]``, padded past the episode end by repeating its last action),
    ``mask`` (bool ``[H]``: True for real actions, False for padding), ``history`` (float32 ``[n_obs, ...]``: the
    observations ``o[t - n_obs + 1 : t + 1]``, oldest first, the episode's first observation repeated before its
    start, as Diffusion Policy pads), ``episode`` and ``t`` (ints). The two fields are loaded into memory once.

    Args:
        store: the episodes.
        episodes: indices of the episodes to use (``0 <= i < store.n_episodes``).
        horizon: chunk length ``H >= 1``.
        n_obs: observation frames per item ``>= 1`` (``history``).
        obs_key, action_key: the store fields holding observations and actions.
        hindsight: relabel each episode's goal keypoints with its object's last ones
            (:class:`~kpflow.data.hindsight.HindsightGoals`; None: the goals as recorded).
        relabel_fragments: with ``hindsight``, relabel fragments of longer episodes (correction takeovers) too;
            False (the default, for learning): they keep their recorded goal (:mod:`kpflow.data.hindsight`).
    """

    def __init__(
        self,
        store: EpisodeStore,
        episodes: Sequence[int],
        horizon: int = 20,
        obs_key: str = "keypoints",
        action_key: str = "action",
        n_obs: int = 1,
        hindsight: HindsightGoals | None = None,
        relabel_fragments: bool = False,
    ) -> None:
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1; got {horizon}")
        if n_obs < 1:
            raise ValueError(f"n_obs must be >= 1; got {n_obs}")
        for key in (obs_key, action_key):
            if key not in store.fields:
                raise ValueError(f"field {key!r} not in {store.path}; available fields: {store.fields}")
        episodes = [int(i) for i in episodes]
        bad = [i for i in episodes if not 0 <= i < store.n_episodes]
        if bad:
            raise ValueError(f"episode indices {bad} out of range 0..{store.n_episodes - 1} of {store.path}")
        self.horizon, self.n_obs = horizon, n_obs
        self.obs = np.ascontiguousarray(store.field(obs_key), dtype=np.float32)
        if hindsight is not None:
            keep = None if relabel_fragments else fragment_episodes(store)
            self.obs = hindsight.relabel(self.obs, store.episode_ends, keep)
        self.actions = np.ascontiguousarray(store.field(action_key), dtype=np.float32)
        # Per item: its episode, local step t, and the episode's start/end rows in the concatenated arrays.
        slices = [store.episode_slice(i) for i in episodes]
        starts = np.array([s.start for s in slices], dtype=np.int64)
        stops = np.array([s.stop for s in slices], dtype=np.int64)
        lengths = stops - starts
        self._episode = np.repeat(np.array(episodes, dtype=np.int64), lengths)
        self._t = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths)
        self._row = np.repeat(starts, lengths) + self._t
        self._end = np.repeat(stops, lengths)
        self._start = np.repeat(starts, lengths)

    def __len__(self) -> int:
        return len(self._row)

    @property
    def steps(self) -> np.ndarray:
        """Each item's step ``t`` within its episode ``[N]``."""
        return self._t

    def previous_action(self, k: int) -> np.ndarray:
        """The action taken before item ``k``'s step (its own at an episode's first step)."""
        row = int(self._row[k])
        return self.actions[row - 1 if self._t[k] > 0 else row]

    def episode_actions(self, episode: int) -> np.ndarray:
        """The recorded actions ``[T, A]`` of ``episode`` (one of this dataset's)."""
        return self.actions[self._row[self._episode == episode]]

    def arrays(self, items: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Observations ``[n, ...]``, action chunks ``[n, H, A]`` and masks ``[n, H]`` of ``items`` (all by default)."""
        row, end = self._row[items], self._end[items]
        rows = row[..., None] + np.arange(self.horizon)
        return self.obs[row], self.actions[np.minimum(rows, end[..., None] - 1)], rows < end[..., None]

    def episodes(self, items: np.ndarray | slice = slice(None)) -> np.ndarray:
        """The store's episode index of each of ``items`` ``[n]``."""
        return self._episode[items]

    def history(self, items: np.ndarray | slice = slice(None)) -> np.ndarray:
        """Observation histories ``[n, n_obs, ...]`` of ``items``: rows ``t - n_obs + 1 .. t``, clamped to the episode start."""
        row, start = self._row[items], self._start[items]
        rows = row[..., None] + np.arange(1 - self.n_obs, 1)
        return self.obs[np.maximum(rows, start[..., None])]

    def __getitem__(self, k: int) -> dict[str, torch.Tensor | int]:
        if not -len(self) <= k < len(self):
            raise IndexError(f"item {k} out of range for {len(self)} items")
        obs, actions, mask = self.arrays(k)
        return {
            "obs": torch.from_numpy(obs.copy()),
            "actions": torch.from_numpy(actions),
            "mask": torch.from_numpy(mask),
            "history": torch.from_numpy(self.history(k)),
            "episode": int(self._episode[k]),
            "t": int(self._t[k]),
        }


def split_episodes(n_episodes: int, val_fraction: float = 0.1, seed: int = 0) -> tuple[list[int], list[int]]:
    """Split episode indices ``0..n_episodes-1`` into sorted ``(train, val)`` lists at random, by ``seed``.

    Validation gets ``round(val_fraction * n_episodes)`` episodes, at least one when ``val_fraction > 0``,
    and training always keeps at least one; so validation is empty only if ``n_episodes == 1`` or
    ``val_fraction == 0``.
    """
    if n_episodes < 1:
        raise ValueError(f"need at least one episode to split; got n_episodes={n_episodes}")
    if not 0 <= val_fraction < 1:
        raise ValueError(f"val_fraction must be in [0, 1); got {val_fraction}")
    n_val = max(1, round(val_fraction * n_episodes)) if val_fraction > 0 else 0
    n_val = min(n_val, n_episodes - 1)
    order = np.random.default_rng(seed).permutation(n_episodes)
    return sorted(order[n_val:].tolist()), sorted(order[:n_val].tolist())


#: Diffusion Policy's raw Push-T replay buffer (pusht_cchi_v7_replay.zarr): its arrays, and the command that imports it
DP_REPLAY_ARRAYS = ("data/state", "data/action", "data/keypoint", "meta/episode_ends")
DP_REPLAY_IMPORT = "python -m kpflow.tasks.pusht.replay_import"


def raw_replay_help(path: Path, obs_key: str) -> str | None:
    """What to do when ``path`` is Diffusion Policy's raw Push-T replay buffer (it has :data:`DP_REPLAY_ARRAYS` and no
    field ``obs_key``), read from its folder before it is opened; None for anything else."""
    if (path / "data" / obs_key).exists() or not all((path / name).exists() for name in DP_REPLAY_ARRAYS):
        return None
    return (
        f"{path} is Diffusion Policy's raw Push-T replay buffer ({', '.join(DP_REPLAY_ARRAYS)}; its keypoint is the "
        f"block's 9 points, without the agent or the goal), not a kpflow store: it has no field {obs_key!r}. Import it "
        f"once into a store with kpflow's 25 keypoints: {DP_REPLAY_IMPORT} {path} (into kpflow's data folder, "
        f"kpflow/utils/data_dir.py), then train on that: data=pusht_human"
    )


class ChunkDataModule(lightning.LightningDataModule):
    """Train/val :class:`ChunkDataset` s from the episode store at ``path``, split by episode.

    Args:
        path: an episode store (opened read-only) or a LeRobot v3 dataset folder (read through a temporary store,
            :func:`~kpflow.data.lerobot_dataset.open_lerobot`: its ``observation.state`` named ``k<i>.<axis>``, or
            mapped by ``keypoint_map``, becomes ``keypoints [T, K, D]``, its ``action`` the ``action``).
        horizon, n_obs, obs_key, action_key: see :class:`ChunkDataset`.
        val_fraction, seed: see :func:`split_episodes`; ``seed`` also fixes the training shuffle order.
        max_episodes: use only the first ``max_episodes`` episodes (all if None).
        hindsight, relabel_fragments: see :class:`ChunkDataset`.
        keypoint_map: for a LeRobot dataset whose ``observation.state`` is not named ``k0.x, k0.y, ...``: which of its
            columns are keypoints and which the robot's (:class:`~kpflow.data.lerobot_dataset.KeypointMap`, or its
            config ``{keypoints: {name: [x, y(, z)], ...}, robot: [x, y(, z)]}``); None: the names say it.
    """

    def __init__(
        self,
        path: str | Path,
        horizon: int = 20,
        obs_key: str = "keypoints",
        action_key: str = "action",
        val_fraction: float = 0.1,
        batch_size: int = 256,
        num_workers: int = 0,
        seed: int = 0,
        max_episodes: int | None = None,
        n_obs: int = 1,
        hindsight: HindsightGoals | None = None,
        relabel_fragments: bool = False,
        keypoint_map: KeypointMap | Mapping | None = None,
    ) -> None:
        super().__init__()
        if max_episodes is not None and max_episodes < 1:
            raise ValueError(f"max_episodes must be >= 1 or None; got {max_episodes}")
        self.path, self.horizon, self.obs_key, self.action_key = Path(path), horizon, obs_key, action_key
        self.val_fraction, self.batch_size, self.num_workers = val_fraction, batch_size, num_workers
        self.seed, self.max_episodes, self.n_obs, self.hindsight = seed, max_episodes, n_obs, hindsight
        self.relabel_fragments = relabel_fragments
        self.keypoint_map = None if keypoint_map is None else KeypointMap.from_config(keypoint_map)
        self.train_episodes: list[int] | None = None
        self.val_episodes: list[int] | None = None
        self.train_set: ChunkDataset | None = None
        self.val_set: ChunkDataset | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        lerobot = is_lerobot(self.path)
        if not lerobot and self.keypoint_map is not None:
            raise ValueError(f"data.keypoint_map maps a LeRobot dataset's observation.state, but {self.path} is not one (no meta/info.json): "
                             f"an episode store's field {self.obs_key!r} is read as it is; leave keypoint_map out (null)")  # fmt: skip
        if not lerobot and (raw := raw_replay_help(self.path, self.obs_key)):
            raise ValueError(raw)
        store = open_lerobot(self.path, self.keypoint_map) if lerobot else EpisodeStore(self.path, mode="r")
        if missing := [k for k in (self.obs_key, self.action_key) if k not in store.fields]:
            if lerobot:
                raise ValueError(naming_help(self.path, missing[0], list(store.fields)))
            raise ValueError(f"{self.path} has no field {missing[0]!r} (it has {list(store.fields)}): training reads keypoints [T, K, D] "
                             f"and actions [T, A]; with data=store, name its fields with data.obs_key=FIELD and data.action_key=FIELD")  # fmt: skip
        n = store.n_episodes if self.max_episodes is None else min(store.n_episodes, self.max_episodes)
        if n == 0:
            raise ValueError(f"{self.path} holds no episodes")
        self.train_episodes, self.val_episodes = split_episodes(n, self.val_fraction, self.seed)
        kwargs = dict(
            horizon=self.horizon,
            obs_key=self.obs_key,
            action_key=self.action_key,
            n_obs=self.n_obs,
            hindsight=self.hindsight,
            relabel_fragments=self.relabel_fragments,
        )
        self.train_set = ChunkDataset(store, self.train_episodes, **kwargs)
        self.val_set = ChunkDataset(store, self.val_episodes, **kwargs)

    #: the model keys :meth:`model_dims` reads from the data
    MODEL_DIMS = ("n_keypoints", "keypoint_dim", "action_dim")

    def model_dims(self) -> dict[str, int]:
        """What the data says a policy's size must be: ``n_keypoints``, ``keypoint_dim`` (the observations' ``[K, D]``)
        and ``action_dim`` (``train`` fills the model keys a config leaves null with these; sets the data up)."""
        self.setup()
        obs, actions = self.train_set.obs, self.train_set.actions
        if obs.ndim != 3 or actions.ndim != 2:
            raise ValueError(
                f"{self.path}: a K-CFM observes keypoints [T, K, D] and acts [T, A], but field {self.obs_key!r} is"
                f" {list(obs.shape)} and {self.action_key!r} {list(actions.shape)} (a LeRobot dataset's observation.state"
                " is read as keypoints when its names are k0.x, k0.y, ... or data.keypoint_map says which columns are"
                " keypoints: kpflow.data.lerobot_dataset)"
            )
        return dict(zip(self.MODEL_DIMS, (int(obs.shape[1]), int(obs.shape[2]), int(actions.shape[1]))))

    def training_chunks(self) -> TrainingChunks:
        """The training episodes' rows (:class:`TrainingChunks`), what a model's processor is fitted to before
        training (``model.fit_processor(datamodule.training_chunks())``; sets the data up)."""
        self.setup()
        keypoints, chunks, mask = self.train_set.arrays()
        return TrainingChunks(keypoints, chunks, mask, self.train_set.horizon, self.train_set.n_obs)

    def _loader(self, dataset: ChunkDataset | None, shuffle: bool) -> DataLoader:
        if dataset is None:
            raise RuntimeError("call setup() before asking for a dataloader")
        generator = torch.Generator().manual_seed(self.seed) if shuffle else None
        return DataLoader(dataset, self.batch_size, shuffle=shuffle, generator=generator, num_workers=self.num_workers)

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_set, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_set, shuffle=False)
