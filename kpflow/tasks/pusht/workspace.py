"""Push-T workspaces: the standard 512 x 512 arena and a large 1024 x 1024 one for out-of-distribution tests."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Workspace:
    """A square arena of ``size`` pixels with walls at ``wall_lo``/``wall_hi`` and a square training region.

    The standard env's walls run from (5, 5) to (506, 506) in a 512-px arena; larger arenas keep the same margins.
    The training region is the top-left ``region`` x ``region`` square (the whole arena for ``standard``).
    """

    name: str
    size: int
    region: int = 512

    @property
    def wall_lo(self) -> float:
        return 5.0

    @property
    def wall_hi(self) -> float:
        return float(self.size - 6)

    def in_region(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Whether each point ``[..., 2]`` lies in the training region, at least ``margin`` px inside it."""
        p = np.asarray(points, float)
        return np.all((p >= margin) & (p <= self.region - margin), axis=-1)

    def in_walls(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Whether each point ``[..., 2]`` lies inside the walls, at least ``margin`` px from them."""
        p = np.asarray(points, float)
        return np.all((p >= self.wall_lo + margin) & (p <= self.wall_hi - margin), axis=-1)


WORKSPACES = {"standard": Workspace("standard", 512), "large": Workspace("large", 1024)}


def get_workspace(name: str | Workspace) -> Workspace:
    if isinstance(name, Workspace):
        return name
    if name not in WORKSPACES:
        raise ValueError(f"unknown Push-T workspace {name!r}; choose one of {sorted(WORKSPACES)}")
    return WORKSPACES[name]
