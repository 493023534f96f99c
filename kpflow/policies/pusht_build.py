"""Policies built from configuration (``conf/policy/*.yaml``): plain functions that Hydra instantiates."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Callable

from ..data.chunks import ChunkDataModule
from ..data.episode_store import EpisodeStore
from ..data.source_index import PUSHT_BLOCK, PUSHT_GOAL, SourceIndex, pusht_weights
from ..maps import ILWRMap
from ..maps.base import TransportMap
from ..maps.learned import check_map_factory
from ..tasks.base import PolicyLayout
from ..tasks.pusht.geometry import N_KEYPOINTS
from ..tasks.pusht.task import PushTTask
from .checks import INPUT_MARGIN
from .chunk_transport import TransportPolicy
from .nearest import NearestNeighbourPolicy

FRAMES = {"world": None, "block": PUSHT_BLOCK}
#: the keypoints a Push-T map is fitted on (see :mod:`.chunk_transport`): all 25, or the block's 12 and the agent
FIT_ON = {"all": None, "block_agent": (*PUSHT_BLOCK, 2 * len(PUSHT_BLOCK))}


def check_checkpoint_fits(checkpoint: str, hparams: Mapping, task=None) -> None:
    """Raise ``ValueError`` naming ``checkpoint`` unless the keypoint layout of the K-CFM it holds (its
    hyper-parameters ``n_keypoints``, ``keypoint_dim``, ``action_dim``) is the ``policy_layout`` that ``task``
    declares (None: Push-T's): a checkpoint of another task is refused while the run is being built, before any
    episode."""
    task = task or PushTTask()
    name, want = task.name, task.policy_layout
    have = PolicyLayout(int(hparams["n_keypoints"]), int(hparams["keypoint_dim"]), int(hparams["action_dim"]))
    if have != want:
        raise ValueError(
            f"{checkpoint} is a policy for {have.n_keypoints} keypoints in {have.keypoint_dim}-D and {have.action_dim}-D "
            f"actions, but {name} shows {want.n_keypoints} keypoints in {want.keypoint_dim}-D and takes "
            f"{want.action_dim}-D actions: pass a checkpoint trained on {name}"
        )


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
    (:class:`~.source_choice.SourceChoice`). A learned map is read now and checked against the keypoints it is
    fitted on (:func:`~kpflow.maps.learned.check_map_factory`)."""
    fit = fit_on_indices(fit_on)
    check_map_factory(make_map, len(fit) if fit else N_KEYPOINTS, 2, f"Push-T's transport (fit_on={fit_on})")
    return TransportPolicy(pusht_index(demos, horizon, weights, frame), make_map, execute, fit_on=fit, **options)


def within_reach(policy, reach: float | None, turn_deg: float | None = None):
    """``policy`` shown its Push-T goal at most ``reach`` px from the block and turned at most ``turn_deg`` degrees
    from it (:class:`~.subgoal.SubgoalPolicy`); as it is when both are None."""
    from .subgoal import SubgoalPolicy

    if reach is None and turn_deg is None:
        return policy
    return SubgoalPolicy(policy, PUSHT_BLOCK, PUSHT_GOAL, reach, turn_deg)


def kcfm(checkpoint: str, steps: int = 10, execute: int = 8, reach: float | None = None, turn_deg: float | None = None, task=None,
         input_margin: float | None = INPUT_MARGIN):  # fmt: skip
    """The K-CFM at ``checkpoint`` for ``task`` (None: Push-T), shown its goal within ``reach`` px and ``turn_deg``
    degrees of the block when given (:func:`within_reach`), refusing observations farther than ``input_margin``
    box extents outside its training keypoints (:class:`~.kcfm_policy.KCFMPolicy`). A checkpoint trained on another
    task's keypoints or actions is refused here, naming both layouts (:func:`check_checkpoint_fits`)."""
    from .kcfm_policy import KCFMPolicy

    policy = KCFMPolicy.from_checkpoint(checkpoint, steps, execute, input_margin)
    check_checkpoint_fits(checkpoint, policy.model.hparams, task)
    return within_reach(policy, reach, turn_deg)


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
    input_margin: float | None = INPUT_MARGIN,
    **options,
):
    """:class:`~.transported_kcfm.TransportedKCFMPolicy` of the K-CFM at ``checkpoint`` over the demonstrations' index,
    its map fitted on the keypoints ``fit_on`` names (:data:`FIT_ON`), shown its goal within ``reach`` px and
    ``turn_deg`` degrees of the block when given (:func:`within_reach`: the source search then looks for that goal);
    ``options``: its source selection and stuck detection (:class:`~.source_choice.SourceChoice`). The checkpoint
    must be a Push-T K-CFM (:func:`check_checkpoint_fits`) and a learned map is read now and checked against the
    keypoints it is fitted on, both before the demonstrations are built."""
    from hydra.utils import instantiate

    from .kcfm_policy import KCFMPolicy
    from .transported_kcfm import TransportedKCFMPolicy

    fit = fit_on_indices(fit_on)
    model = KCFMPolicy.from_checkpoint(checkpoint, steps, execute, input_margin).model  # first: a refused file collects nothing
    check_checkpoint_fits(checkpoint, model.hparams)
    if isinstance(make_map, Mapping) and "_target_" in make_map:
        make_map = instantiate(make_map)
    check_map_factory(make_map, len(fit) if fit else N_KEYPOINTS, 2, f"Push-T's transported K-CFM (fit_on={fit_on})")
    if isinstance(demos, Mapping) and "_target_" in demos:
        demos = instantiate(demos)
    index = pusht_index(demos, model.hparams.horizon, weights, frame)
    policy = TransportedKCFMPolicy(model, index, make_map, steps, execute, pull_back, fit, input_margin, **options)
    return within_reach(policy, reach, turn_deg)
