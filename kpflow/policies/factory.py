"""The one policy builder: every policy of every task, built from configuration (``kpflow/conf/policy/*.yaml``, plain
functions Hydra instantiates) for ``evaluate`` and ``correct``, and from a checkpoint for ``serve``
(:func:`make_kcfm`, :func:`make_transported_kcfm`).

What is task-specific comes from the task's :class:`~.base.PolicyLayout`: the keypoints' dimension, their named
groups and roles (``objects``, ``goals``, ``robot``) and whether actions carry a rotation. Options that name
keypoints take group or role names: the source search's ``weights`` and ``frame`` (:class:`~.source_search.SourceSearch`,
one options object for every transporting policy) and ``fit_on`` (the keypoints a map is fitted on, or ``all``). Push-T's groups are ``block``,
``goal``, ``agent``; a robosuite task's are its object, its target and ``gripper``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Callable

from ..data.chunks import ChunkDataModule
from ..data.source_index import SourceIndex
from ..maps import ILWRMap
from ..maps.base import TransportMap
from ..maps.learned import check_map_factory
from ..utils.releases import resolve_release
from .base import PolicyLayout
from .checks import INPUT_MARGIN
from .chunk_transport import TransportPolicy
from .nearest import NearestNeighbourPolicy
from .source_search import SourceSearch
from .symmetry import ArmLimits


def source_index_path(checkpoint: str | Path) -> Path:
    """Where a transporting policy's source index lives (:meth:`SourceIndex.save`): beside its checkpoint, named
    after it (``<name>.ckpt`` -> ``<name>.source_index.npz``)."""
    checkpoint = resolve_release(checkpoint)
    return checkpoint.with_name(f"{checkpoint.stem}.source_index.npz")


def _built(node):
    """A Hydra node instantiated (``_target_``), anything else as it is."""
    if isinstance(node, Mapping) and "_target_" in node:
        from hydra.utils import instantiate

        return instantiate(node)
    return node


def layout_of(task) -> PolicyLayout:
    """The :class:`PolicyLayout` a task declares (``task.policy_layout``; the task may be a config node)."""
    layout = getattr(_built(task), "policy_layout", None)
    if not isinstance(layout, PolicyLayout):
        raise ValueError(f"{type(task).__name__} declares no policy_layout: a learned or transporting policy needs the task's keypoint layout")
    return layout


def check_checkpoint_fits(checkpoint: str, hparams: Mapping, task) -> None:
    """Raise ``ValueError`` naming ``checkpoint`` unless the keypoint layout of the K-CFM it holds (its
    hyper-parameters ``n_keypoints``, ``keypoint_dim``, ``action_dim``) is the one ``task`` declares: a checkpoint
    of another task is refused while the run is being built, before any episode."""
    task = _built(task)
    want = layout_of(task)
    have = (int(hparams["n_keypoints"]), int(hparams["keypoint_dim"]), int(hparams["action_dim"]))
    if have != want.shape:
        raise ValueError(
            f"{checkpoint} is a policy for {have[0]} keypoints in {have[1]}-D and {have[2]}-D actions, but {task.name} "
            f"shows {want.n_keypoints} keypoints in {want.keypoint_dim}-D and takes {want.action_dim}-D actions: pass a "
            f"checkpoint trained on {task.name}"
        )


def fit_on_indices(layout: PolicyLayout, fit_on: str | Sequence[str]) -> tuple[int, ...] | None:
    """The keypoint indices a map is fitted on: ``"all"`` (None: every keypoint) or group and role names."""
    if isinstance(fit_on, str):
        if fit_on == "all":
            return None
        fit_on = [fit_on]
    return layout.indices(*fit_on)


def within_reach(policy, layout: PolicyLayout, reach: float | None, turn_deg: float | None = None):
    """``policy`` shown its goal at most ``reach`` from its object and turned at most ``turn_deg`` degrees from it
    (:class:`~.subgoal.SubgoalPolicy`, planar tasks); as it is when both are None."""
    from .subgoal import SubgoalPolicy

    if reach is None and turn_deg is None:
        return policy
    if layout.keypoint_dim != 2 or not layout.indices("goals"):
        raise ValueError("reach and turn_deg show a planar task's goal nearer its object: this task has no planar goal")
    return SubgoalPolicy(policy, layout.indices("objects"), layout.indices("goals"), reach, turn_deg)


def _map_factory(make_map, layout: PolicyLayout, fit: tuple[int, ...] | None, what: str):
    make_map = _built(make_map)
    check_map_factory(make_map, len(fit) if fit else layout.n_keypoints, layout.keypoint_dim, what)
    return make_map


def make_kcfm(model, layout: PolicyLayout, steps: int | None = None, execute: int | None = None, input_margin: float | None = INPUT_MARGIN,
              reach: float | None = None, turn_deg: float | None = None, solver: str | None = None):  # fmt: skip
    """A loaded K-CFM as a policy (:class:`~.kcfm.policy.KCFMPolicy`), its goal within ``reach``/``turn_deg``; None:
    the checkpoint's own settings (:mod:`.settings`; ``reach``/``turn_deg`` False: the goal as observed)."""
    from .kcfm.policy import KCFMPolicy

    limits = model.settings.given(reach=reach, turn_deg=turn_deg)
    return within_reach(KCFMPolicy(model, steps, execute, input_margin, solver), layout, limits.reach, limits.turn_deg)


def make_transported_kcfm(model, index: SourceIndex, layout: PolicyLayout, make_map: Callable[[], TransportMap] = ILWRMap,
                          steps: int | None = None, execute: int | None = None, pull_back: str = "agent", fit_on: Sequence[int] | None = None,
                          input_margin: float | None = INPUT_MARGIN, reach: float | None = None, turn_deg: float | None = None,
                          solver: str | None = None, segments: bool = False, search: SourceSearch | Mapping | None = None,
                          arm: ArmLimits | None = None, alternatives: int = 3):  # fmt: skip
    """A loaded K-CFM transported online over ``index`` (:class:`~.transported_kcfm.TransportedKCFMPolicy`), phase
    by phase with ``segments`` (the layout's phases), its source chosen as ``search`` says
    (:class:`~.source_search.SourceSearch`: its choice; the index carries the weights and frame), each chunk checked
    against ``arm`` (the layout's symmetric correspondences chosen by its cost, up to ``alternatives`` sources
    tried); ``steps``, ``solver``, ``execute``, ``reach`` and ``turn_deg`` as in :func:`make_kcfm`."""
    from .transported_kcfm import TransportedKCFMPolicy

    choice = SourceSearch.of(search).choice()
    policy = TransportedKCFMPolicy(model, index, make_map, steps, execute, pull_back, fit_on, input_margin, layout, solver, segments, arm,
                                   alternatives, **choice)  # fmt: skip
    limits = model.settings.given(reach=reach, turn_deg=turn_deg)
    return within_reach(policy, layout, limits.reach, limits.turn_deg)


def nearest(demos: ChunkDataModule, task, horizon: int = 20, execute: int = 8, search: SourceSearch | Mapping | None = None,
            relative: bool = False):  # fmt: skip
    """Nearest neighbour over the demonstrations (:class:`~.nearest.NearestNeighbourPolicy`), compared with
    ``search``'s weights and frame (its choice unused: the nearest)."""
    index = SourceSearch.of(search).index(_built(demos), layout_of(task), horizon)
    return NearestNeighbourPolicy(index, execute, relative)


def transport(demos: ChunkDataModule, task, make_map: Callable[[], TransportMap] = ILWRMap, horizon: int = 20,
              search: SourceSearch | Mapping | None = None, execute: int = 8, fit_on: str | Sequence[str] = "all",
              max_step_px: float | None = None):  # fmt: skip
    """Policy transportation (:class:`~.chunk_transport.TransportPolicy`) over the demonstrations' index, its source
    found as ``search`` says (:class:`~.source_search.SourceSearch`), its map fitted on ``fit_on``, each executed
    step clipped to ``max_step_px``. A learned map is read now and checked against the keypoints it is fitted on."""
    layout, search = layout_of(task), SourceSearch.of(search)
    fit = fit_on_indices(layout, fit_on)
    make_map = _map_factory(make_map, layout, fit, f"policy transportation (fit_on={fit_on})")
    return TransportPolicy(search.index(_built(demos), layout, horizon), make_map, execute, max_step_px, fit, layout, **search.choice())


def kcfm(checkpoint: str, task, steps: int | None = None, execute: int | None = None, reach: float | None = None, turn_deg: float | None = None,
         input_margin: float | None = INPUT_MARGIN, solver: str | None = None):  # fmt: skip
    """The K-CFM at ``checkpoint`` for ``task`` (:func:`make_kcfm`; ``steps``/``solver`` None: the checkpoint's); a
    checkpoint trained on another task's keypoints or actions is refused here, naming both layouts
    (:func:`check_checkpoint_fits`)."""
    from .kcfm.policy import KCFMPolicy

    model = KCFMPolicy.from_checkpoint(checkpoint, steps, execute, input_margin, solver).model
    check_checkpoint_fits(checkpoint, model.hparams, task)
    return make_kcfm(model, layout_of(task), steps, execute, input_margin, reach, turn_deg, solver)


def transported_kcfm(checkpoint: str, demos: ChunkDataModule | Mapping | None, task, make_map: Callable[[], TransportMap] | Mapping = ILWRMap,
                     steps: int | None = None, execute: int | None = None, search: SourceSearch | Mapping | None = None, pull_back: str = "agent",
                     fit_on: str | Sequence[str] = "all", reach: float | None = None, turn_deg: float | None = None,
                     input_margin: float | None = INPUT_MARGIN, solver: str | None = None, segments: bool = False, arm: bool = False,
                     alternatives: int = 3):  # fmt: skip
    """The K-CFM at ``checkpoint`` transported online over the index of its demonstrations ``demos`` (None: the
    index saved beside the checkpoint, :func:`source_index_path`) (:func:`make_transported_kcfm`), its source found
    as ``search`` says (:class:`~.source_search.SourceSearch`), its map fitted on ``fit_on`` (with ``segments``:
    phase by phase, each phase's map, search frame and weights as the task declares them); with ``arm``, each chunk
    checked against the task's ``arm_limits`` and the symmetric correspondence chosen by their cost. The checkpoint
    is checked against the task and a learned map against the keypoints it is fitted on, before the
    demonstrations are built (the config is not instantiated recursively: a refused file collects nothing)."""
    from .kcfm.policy import KCFMPolicy

    task = _built(task)
    layout = layout_of(task)
    limits = getattr(task, "arm_limits", None) if arm else None
    if arm and limits is None:
        raise ValueError(f"arm=true checks chunks against the task's arm_limits; {type(task).__name__} declares none")
    model = KCFMPolicy.from_checkpoint(checkpoint, steps, execute, input_margin, solver).model
    check_checkpoint_fits(checkpoint, model.hparams, task)
    fit = fit_on_indices(layout, fit_on)
    make_map = _map_factory(make_map, layout, fit, f"the transported K-CFM (fit_on={fit_on})")
    search = SourceSearch.of(search)
    if demos is None:
        index = search.reindexed(SourceIndex.load(source_index_path(checkpoint)), layout)
    else:
        index = search.index(_built(demos), layout, int(model.hparams.horizon))
    return make_transported_kcfm(model, index, layout, make_map, steps, execute, pull_back, fit, input_margin, reach, turn_deg, solver, segments,
                                 search, limits, alternatives)  # fmt: skip
