"""Policies built from configuration (``conf/policy/*.yaml``): plain functions that Hydra instantiates."""

from __future__ import annotations

from typing import Callable

from ..data.demos import ensure_pusht_demos
from ..maps import ILWRMap
from ..maps.base import TransportMap
from .nearest import NearestNeighbourPolicy
from .source_index import PUSHT_BLOCK, SourceIndex, pusht_weights
from .transportation import TransportationPolicy

FRAMES = {"world": None, "block": PUSHT_BLOCK}


def pusht_index(demos: dict, horizon: int = 20, weights: dict | None = None, frame: str = "block") -> SourceIndex:
    """A :class:`SourceIndex` over every step of the expert demonstrations described by ``demos``."""
    if frame not in FRAMES:
        raise ValueError(f"unknown search frame {frame!r}; choose one of {sorted(FRAMES)}")
    store = ensure_pusht_demos(**demos)
    return SourceIndex.from_store(store, horizon, pusht_weights(**(weights or {})), FRAMES[frame])


def nearest(
    demos: dict,
    horizon: int = 20,
    execute: int = 8,
    weights: dict | None = None,
    frame: str = "block",
    relative: bool = False,
):
    return NearestNeighbourPolicy(pusht_index(demos, horizon, weights, frame), execute, relative)


def transportation(
    demos: dict,
    make_map: Callable[[], TransportMap] = ILWRMap,
    horizon: int = 20,
    execute: int = 8,
    weights: dict | None = None,
    frame: str = "block",
    candidates: int = 1,
    temperature: float = 1.2,
    max_step_px: float | None = None,
    stuck_decisions: int | None = None,
    stuck_px: float = 2.0,
    stuck_candidates: int = 50,
):
    index = pusht_index(demos, horizon, weights, frame)
    return TransportationPolicy(index, make_map, execute, candidates, temperature, max_step_px, stuck_decisions, stuck_px, stuck_candidates)


def kcfm(checkpoint: str, steps: int = 10, execute: int = 8):
    from .kcfm_policy import KCFMPolicy

    return KCFMPolicy.from_checkpoint(checkpoint, steps, execute)


def transported_kcfm(
    checkpoint: str,
    demos: dict,
    make_map: Callable[[], TransportMap] = ILWRMap,
    steps: int = 10,
    execute: int = 8,
    weights: dict | None = None,
    frame: str = "block",
    pull_back: str = "agent",
):
    from .kcfm_policy import KCFMPolicy
    from .transported_kcfm import TransportedKCFMPolicy

    model = KCFMPolicy.from_checkpoint(checkpoint, steps, execute).model
    index = pusht_index(demos, model.hparams.horizon, weights, frame)
    return TransportedKCFMPolicy(model, index, make_map, steps, execute, pull_back)
