"""Demonstrated states and their action chunks, searchable by weighted keypoint distance.

The distance between two keypoint sets ``p, q [K, D]`` is ``d(p, q) = sum_k w_k |p_k - q_k|^2`` with one weight per
keypoint (Push-T: one for the block's 12, one for the goal's 12, one for the agent, as
:func:`kpflow.tasks.pusht.geometry.pusht_weights` gives them). Scaling each keypoint by ``sqrt(w_k)`` turns it into
a squared Euclidean distance between flat feature vectors ``f``, and ``|f - g|^2 = |f|^2 - 2 f.g + |g|^2`` makes a
query one matrix-vector product over all sources (BLAS, float32).

With ``reference`` keypoints (Push-T: the block's 12) every set is first moved rigidly so that its reference
keypoints best match (Kabsch: :func:`~kpflow.geometry.alignment.fit_affine`) those of the first source: configurations are
then compared by where things are relative to the object, whatever the object's pose in the workspace. That is what
makes a demonstrated chunk transportable to a block somewhere else: the map takes care of the rigid motion.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..geometry.alignment import fit_affine
from ..utils.config_checks import Key
from ..utils.formats import read_npz
from ..utils.io import atomic_path
from .chunks import ChunkDataset
from .episode_store import EpisodeStore
from .hindsight import HindsightGoals


class SourceIndex:
    """Source keypoint sets ``[N, K, D]`` with the action chunk ``[N, H, A]`` demonstrated from each, and optionally
    the demonstration each belongs to (``episodes [N]``: the rows of one episode are consecutive, in time order).

    :meth:`query` returns the index of the source nearest to a keypoint set under the weighted distance.
    """

    def __init__(
        self,
        keypoints: np.ndarray,
        chunks: np.ndarray,
        weights: np.ndarray | None = None,
        reference: tuple[int, ...] | None = None,
        episodes: np.ndarray | None = None,
    ):
        keypoints = np.asarray(keypoints, dtype=np.float32)
        chunks = np.asarray(chunks, dtype=np.float32)
        if keypoints.ndim != 3 or chunks.ndim != 3 or len(keypoints) != len(chunks):
            raise ValueError(f"need keypoints [N, K, D] and chunks [N, H, A]; got {keypoints.shape} and {chunks.shape}")
        if len(keypoints) == 0:
            raise ValueError("a source index needs at least one source")
        if not (np.isfinite(keypoints).all() and np.isfinite(chunks).all()):
            raise ValueError("source keypoints or chunks contain NaN or inf")
        k = keypoints.shape[1]
        weights = np.ones(k, np.float32) if weights is None else np.asarray(weights, np.float32)
        if weights.shape != (k,):
            raise ValueError(f"weights must have one entry per keypoint ({k}), got shape {weights.shape}")
        if not (np.isfinite(weights).all() and (weights >= 0).all() and weights.any()):
            raise ValueError(
                f"keypoint weights must be finite, >= 0 and not all 0 (every distance would be NaN or 0); got {weights.tolist()}"
            )
        self.keypoints, self.chunks, self.weights = keypoints, chunks, weights
        if episodes is not None:
            episodes = np.asarray(episodes)
            if episodes.shape != (len(keypoints),) or not np.issubdtype(episodes.dtype, np.integer):
                raise ValueError(
                    f"episodes must hold one integer per source ({len(keypoints)}), got {episodes.dtype} {episodes.shape}"
                )
            episodes = episodes.astype(np.int64)
        self.episodes = episodes
        self.reference = None if reference is None else list(reference)
        if self.reference is not None and not (len(self.reference) >= 2 and all(0 <= r < k for r in self.reference)):
            raise ValueError(f"reference must list at least 2 keypoint indices in 0..{k - 1}, got {reference}")
        self._template = None if self.reference is None else keypoints[0, self.reference].astype(np.float64)
        self._scale = np.sqrt(weights)[:, None]
        self._features = (self.canonical(keypoints) * self._scale).reshape(len(keypoints), -1)
        self._norms = np.einsum("nf,nf->n", self._features, self._features)

    @classmethod
    def from_store(
        cls,
        store: EpisodeStore,
        horizon: int = 20,
        weights: np.ndarray | None = None,
        reference: tuple[int, ...] | None = None,
        episodes=None,
        obs_key: str = "keypoints",
        action_key: str = "action",
        hindsight: HindsightGoals | None = None,
    ) -> "SourceIndex":
        """Every step of the store's episodes (all by default) with its next ``horizon`` actions (padded at the end);
        with ``hindsight``, each episode's goal keypoints are the ones it reached (:mod:`kpflow.data.hindsight`),
        correction takeovers included: a takeover read so is a source that ends exactly on its goal and is found
        only where the observed goal is there too. (Read with their recorded goal instead, as learning does, the
        takeovers of a corrected store halve policy transportation's success with the object outside the training
        region: results/pusht_table1.md.)"""
        episodes = range(store.n_episodes) if episodes is None else episodes
        dataset = ChunkDataset(
            store, episodes, horizon, obs_key, action_key, hindsight=hindsight, relabel_fragments=True
        )
        keypoints, chunks, _ = dataset.arrays()
        return cls(keypoints, chunks, weights, reference, dataset.episodes())

    def save(self, path: str | Path) -> Path:
        """Write the index to ``path`` (compressed ``.npz``: keypoints, chunks, weights, the reference and the episodes
        where known, no pickled objects; a store's keypoints repeat from step to step, so it is about a third of their
        bytes), atomically; :meth:`load` reads it back."""
        reference = np.asarray([] if self.reference is None else self.reference, np.int64)
        episodes = {} if self.episodes is None else {"episodes": self.episodes}
        with atomic_path(path) as tmp:
            np.savez_compressed(
                tmp, keypoints=self.keypoints, chunks=self.chunks, weights=self.weights, reference=reference, **episodes
            )
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "SourceIndex":
        """The index :meth:`save` wrote to ``path`` (read by :func:`~kpflow.utils.formats.read_npz`: nothing in it can
        run code or declare more memory than it holds; the weights are checked as by the constructor).

        Raises ``FileNotFoundError`` for a missing file and ``ValueError`` naming the file for anything else."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no source index at {path}")
        try:
            arrays = read_npz(path, ("keypoints", "chunks", "weights", "reference"), optional=("episodes",))
            reference = tuple(int(r) for r in arrays["reference"]) or None
            return cls(arrays["keypoints"], arrays["chunks"], arrays["weights"], reference, arrays.get("episodes"))
        except ValueError as e:
            raise ValueError(f"{path} is not a usable source index: {e}") from None

    def canonical(self, keypoints: np.ndarray) -> np.ndarray:
        """Keypoint sets ``[B, K, D]`` moved rigidly onto the template's reference pose (unchanged without one)."""
        if self.reference is None:
            return keypoints
        x = torch.from_numpy(keypoints.astype(np.float64))
        template = torch.from_numpy(self._template).expand(len(x), *self._template.shape)
        a, t = fit_affine(x[:, self.reference], template, "rigid")
        return (x @ a.transpose(1, 2) + t[:, None]).numpy().astype(np.float32)

    def __len__(self) -> int:
        return len(self.keypoints)

    def query(self, keypoints: np.ndarray) -> tuple[int, float]:
        """Index of the nearest source to ``keypoints [K, D]`` and its weighted squared distance."""
        d = self._distances(keypoints)
        i = int(np.argmin(d))
        return i, float(max(d[i], 0.0))

    def query_k(self, keypoints: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest sources to ``keypoints [K, D]``, nearest first: indices ``[k]`` and weighted squared
        distances ``[k]`` (ties in index order; fewer when the index holds fewer than ``k``)."""
        Key(int, lo=1).check("k", k)
        d = self._distances(keypoints)
        k = min(int(k), len(d))
        part = np.argpartition(d, k - 1)[:k] if k < len(d) else np.arange(len(d))
        order = part[np.lexsort((part, d[part]))]
        return order, np.maximum(d[order], 0.0)

    def _distances(self, keypoints: np.ndarray) -> np.ndarray:
        q = np.asarray(keypoints, dtype=np.float32)
        if q.shape != self.keypoints.shape[1:]:
            raise ValueError(f"query keypoints must have shape {self.keypoints.shape[1:]}, got {q.shape}")
        if not np.isfinite(q).all():
            raise ValueError("query keypoints contain NaN or inf")
        f = (self.canonical(q[None])[0] * self._scale).reshape(-1)
        return self._norms - 2.0 * (self._features @ f) + f @ f
