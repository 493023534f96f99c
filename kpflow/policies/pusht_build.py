"""Policies built from configuration (``conf/policy/*.yaml``): plain functions that Hydra instantiates."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Callable

from ..data.chunks import ChunkDataModule
from ..data.episode_store import EpisodeStore
from ..data.source_index import PUSHT_BLOCK, PUSHT_GOAL, SourceIndex, pusht_weights
from ..maps import ILWRMap
from ..maps.base import TransportMap
from .chunk_transport import TransportPolicy
from .nearest import NearestNeighbourPolicy

FRAMES = {"world": None, "block": PUSHT_BLOCK}
#: the keypoints a Push-T map is fitted on (see :mod:`.chunk_transport`): all 25, or the block's 12 and the agent
FIT_ON = {"all": None, "block_agent": (*PUSHT_BLOCK, 2 * len(PUSHT_BLOCK))}


def fit_on_indices(name: str) -> tuple[int, ...] | None:
    """The keypoint indices of :data:`FIT_ON` ``name`` (None: all)."""
    if name not in FIT_ON:
        raise ValueError(f"unknown fit_on {name!r}; choose one of {sorted(FIT_ON)}")
    return FIT_ON[name]


def pusht_index(demos: ChunkDataModule, horizon: int = 20, weights: dict | None = None, frame: str = "block") -> SourceIndex:
    """A :class:`SourceIndex` over every step of the demonstrations of ``demos`` (the configured data node, whose
    store exists once it is built: ``conf/data/pusht_*.yaml``), their goals read as the data node says
    (``data.goals``: recorded, or in hindsight)."""
    if frame not in FRAMES:
        raise ValueError(f"unknown search frame {frame!r}; choose one of {sorted(FRAMES)}")
    if not isinstance(demos, ChunkDataModule):
        raise ValueError(f"demos must be a Push-T data node (a ChunkDataModule, data=pusht_*), got {type(demos).__name__}")
    weights = pusht_weights(**(weights or {}))
    return SourceIndex.from_store(EpisodeStore(demos.path), horizon, weights, FRAMES[frame], hindsight=demos.hindsight)


def nearest(
    demos: ChunkDataModule,
    horizon: int = 20,
    execute: int = 8,
    weights: dict | None = None,
    frame: str = "block",
    relative: bool = False,
):
    return NearestNeighbourPolicy(pusht_index(demos, horizon, weights, frame), execute, relative)


def transport(
    demos: ChunkDataModule,
    make_map: Callable[[], TransportMap] = ILWRMap,
    horizon: int = 20,
    weights: dict | None = None,
    frame: str = "block",
    execute: int = 8,
    fit_on: str = "block_agent",
    **options,
):
    """:class:`TransportPolicy` over the demonstrations' index, its map fitted on the keypoints ``fit_on`` names
    (:data:`FIT_ON`); ``options``: ``max_step_px`` and its source selection and stuck detection
    (:class:`~.source_choice.SourceChoice`)."""
    fit = fit_on_indices(fit_on)
    return TransportPolicy(pusht_index(demos, horizon, weights, frame), make_map, execute, fit_on=fit, **options)


def within_reach(policy, reach: float | None, turn_deg: float | None = None):
    """``policy`` shown its Push-T goal at most ``reach`` px from the block and turned at most ``turn_deg`` degrees
    from it (:class:`~.subgoal.SubgoalPolicy`); as it is when both are None."""
    from .subgoal import SubgoalPolicy

    if reach is None and turn_deg is None:
        return policy
    return SubgoalPolicy(policy, PUSHT_BLOCK, PUSHT_GOAL, reach, turn_deg)


def kcfm(checkpoint: str, steps: int = 10, execute: int = 8, reach: float | None = None, turn_deg: float | None = None):
    """The K-CFM at ``checkpoint``, shown its goal within ``reach`` px and ``turn_deg`` degrees of the block when
    given (:func:`within_reach`)."""
    from .kcfm_policy import KCFMPolicy

    return within_reach(KCFMPolicy.from_checkpoint(checkpoint, steps, execute), reach, turn_deg)


def transported_kcfm(
    checkpoint: str,
    demos: ChunkDataModule | Mapping,
    make_map: Callable[[], TransportMap] | Mapping = ILWRMap,
    steps: int = 10,
    execute: int = 8,
    weights: dict | None = None,
    frame: str = "block",
    pull_back: str = "agent",
    fit_on: str = "block_agent",
    reach: float | None = None,
    turn_deg: float | None = None,
    **options,
):
    """:class:`~.transported_kcfm.TransportedKCFMPolicy` of the K-CFM at ``checkpoint`` over the demonstrations' index,
    its map fitted on the keypoints ``fit_on`` names (:data:`FIT_ON`), shown its goal within ``reach`` px and
    ``turn_deg`` degrees of the block when given (:func:`within_reach`: the source search then looks for that goal);
    ``options``: its source selection and stuck detection (:class:`~.source_choice.SourceChoice`)."""
    from hydra.utils import instantiate

    from .kcfm_policy import KCFMPolicy
    from .transported_kcfm import TransportedKCFMPolicy

    fit = fit_on_indices(fit_on)
    model = KCFMPolicy.from_checkpoint(checkpoint, steps, execute).model  # first: a refused file collects nothing
    demos, make_map = (instantiate(x) if isinstance(x, Mapping) and "_target_" in x else x for x in (demos, make_map))
    index = pusht_index(demos, model.hparams.horizon, weights, frame)
    policy = TransportedKCFMPolicy(model, index, make_map, steps, execute, pull_back, fit, **options)
    return within_reach(policy, reach, turn_deg)
