"""The one interface every policy offers: ``reset(seed)`` and ``act(obs) -> action chunk [H, A]``."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Policy(Protocol):
    def reset(self, seed: int | None = None) -> None:
        """Start a new episode (``seed`` makes stochastic policies reproducible)."""

    def act(self, obs: dict) -> np.ndarray:
        """An action chunk ``[H, A]`` for the observation; the caller executes it and asks again."""
