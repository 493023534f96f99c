"""Keypoint pairs for training the learned map (:class:`~kpflow.maps.map_module.MapModule`): a LightningDataModule.

A task's *pair sampler* (``sampler(n, rng) -> (source, target)``, arrays ``[n, N, D]``; Push-T's is
:class:`~kpflow.tasks.pusht.pairs.PushTPairs`) draws the pairs. For each pair this module adds ``n_queries`` query
points, half near the source keypoints (Gaussian, ``jitter`` times the source's RMS spread) and half uniform over
the sources' bounding box widened by half its size, and where a reference map fitted on the pair carries them (the
``teacher``: :class:`~kpflow.maps.ilwr.ILWRMap` by default, fitted in batches; another map family, e.g. the GP, pair
by pair): the distillation targets of the loss. The pairs are drawn once, in
``setup``, from ``seed``: the same config gives the same data.
"""

from __future__ import annotations

from typing import Callable

import lightning
import numpy as np
import torch
from torch.utils.data import BatchSampler, DataLoader, Dataset, RandomSampler, SequentialSampler
from tqdm import tqdm

from ..maps.base import TransportMap
from ..maps.ilwr import ILWRMap
from ..maps.map_module import KeypointPairs

PairSampler = Callable[[int, np.random.Generator], tuple[np.ndarray, np.ndarray]]


def add_queries(
    source: np.ndarray,
    target: np.ndarray,
    n_queries: int,
    rng: np.random.Generator,
    jitter: float = 0.1,
    chunk: int = 2000,
    teacher: Callable[[], TransportMap] = ILWRMap,
) -> KeypointPairs:
    """The pairs with their query points and the ``teacher``'s targets (module docstring), as float32 tensors."""
    src, tgt = torch.from_numpy(np.asarray(source, np.float64)), torch.from_numpy(np.asarray(target, np.float64))
    b, _, d = src.shape
    centre = src.mean(1, keepdim=True)
    spread = (src - centre).square().sum(-1).mean(-1)[:, None, None].sqrt()
    n_near = n_queries // 2
    pick = torch.from_numpy(rng.integers(0, src.shape[1], (b, n_near)))
    near = torch.gather(src, 1, pick[..., None].expand(-1, -1, d)) + jitter * spread * torch.from_numpy(
        rng.standard_normal((b, n_near, d))
    )
    lo, hi = src.amin(1, keepdim=True), src.amax(1, keepdim=True)
    lo, hi = lo - 0.5 * (hi - lo), hi + 0.5 * (hi - lo)
    box = lo + (hi - lo) * torch.from_numpy(rng.random((b, n_queries - n_near, d)))
    queries = torch.cat([near, box], 1)
    targets = torch.empty_like(queries)
    batched = teacher().supports_batch
    steps = range(0, b if n_queries else 0, chunk if batched else 1)
    with torch.no_grad():  # a teacher that fits one pair at a time (the GP: ~3 ms each) shows its progress
        for i in tqdm(
            steps, desc="distillation targets", unit="pair", disable=batched or len(steps) < 1000, mininterval=5.0
        ):
            s = slice(i, i + chunk) if batched else i
            targets[s] = teacher().fit(src[s], tgt[s])(queries[s])
    return KeypointPairs(src.float(), tgt.float(), queries.float(), targets.float())


class _Pairs(Dataset):
    def __init__(self, pairs: KeypointPairs) -> None:
        self.pairs = pairs

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, items) -> KeypointPairs:
        return self.pairs[torch.as_tensor(items)]


class KeypointPairDataModule(lightning.LightningDataModule):
    """Train/val keypoint pairs from ``sampler`` (module docstring).

    Args:
        sampler: the task's pair sampler.
        n_pairs: pairs drawn (``val_fraction`` of them held out for validation).
        n_queries: query points per pair, for the distillation term (``model.distill_weight > 0``); 0: none.
        jitter: spread of the near-keypoint queries, relative to the source's RMS spread.
        teacher: factory of the map whose values at the queries are the distillation targets (default ILWR).
    """

    def __init__(
        self,
        sampler: PairSampler,
        n_pairs: int = 20000,
        val_fraction: float = 0.1,
        n_queries: int = 0,
        jitter: float = 0.1,
        batch_size: int = 256,
        seed: int = 0,
        teacher: Callable[[], TransportMap] | None = None,
    ) -> None:
        super().__init__()
        if n_pairs < 2:
            raise ValueError(f"n_pairs must be >= 2 (one for validation), got {n_pairs}")
        if not 0 < val_fraction < 1:
            raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}")
        if n_queries < 0:
            raise ValueError(f"n_queries must be >= 0, got {n_queries}")
        self.sampler, self.n_pairs, self.val_fraction = sampler, n_pairs, val_fraction
        self.n_queries, self.jitter, self.batch_size, self.seed = n_queries, jitter, batch_size, seed
        self.teacher = teacher if teacher is not None else ILWRMap
        self.train_set: KeypointPairs | None = None
        self.val_set: KeypointPairs | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        rng = np.random.default_rng(self.seed)
        source, target = self.sampler(self.n_pairs, rng)
        source, target = np.asarray(source), np.asarray(target)
        if source.shape != target.shape or source.ndim != 3 or len(source) != self.n_pairs:
            raise ValueError(
                f"the pair sampler must return source and target [{self.n_pairs}, N, D]; got {source.shape} and {target.shape}"
            )
        if not (np.isfinite(source).all() and np.isfinite(target).all()):
            raise ValueError("the pair sampler returned NaN or inf keypoints")
        pairs = add_queries(source, target, self.n_queries, rng, self.jitter, teacher=self.teacher)
        n_val = max(1, round(self.val_fraction * self.n_pairs))
        self.val_set, self.train_set = pairs[:n_val], pairs[n_val:]

    def _loader(self, pairs: KeypointPairs | None, shuffle: bool) -> DataLoader:
        if pairs is None:
            raise RuntimeError("call setup() before asking for a dataloader")
        data = _Pairs(pairs)
        order = (
            RandomSampler(data, generator=torch.Generator().manual_seed(self.seed))
            if shuffle
            else SequentialSampler(data)
        )
        return DataLoader(data, sampler=BatchSampler(order, self.batch_size, drop_last=False), batch_size=None)

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_set, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_set, shuffle=False)
