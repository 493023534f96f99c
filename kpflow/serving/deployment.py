"""A checkpoint made ready to serve: a factory of independent policies and the metadata that describes them.

The server gives every connection its own policy from :attr:`Deployment.make_policy` (its own sampling noise and
last decision), all sharing one loaded model and, for a transported K-CFM, one source index. The source index of a
transporting policy lives beside its checkpoint as ``<name>.source_index.npz`` (:func:`~kpflow.policies.factory.source_index_path`).

With ``max_batch > 1`` the shared model's network is wrapped in a :class:`~kpflow.serving.batching.BatchedNetwork`,
so that the network calls of policies acting at once in different threads run as one forward pass, and every
policy's ``act`` counts as a request in flight on it (:class:`~kpflow.serving.batching.BatchedPolicy`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..data.source_index import SourceIndex
from ..maps.base import TransportMap
from ..policies.base import Policy, PolicyLayout
from ..policies.checks import INPUT_MARGIN
from ..policies.factory import source_index_path
from ..policies.source_search import SourceSearch
from .batching import DEFAULT_MAX_WAIT_MS, BatchedNetwork, BatchedPolicy, check_batching
from .protocol import PolicyMetadata


@dataclass(frozen=True)
class Deployment:
    """``make_policy()`` builds a fresh policy (``reset``/``act``) described by ``metadata``; ``network`` is the
    shared model's batched network when batching is on (None otherwise)."""

    make_policy: Callable[[], Policy]
    metadata: PolicyMetadata
    network: BatchedNetwork | None = None


def sha256(path: str | Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def load_deployment(
    checkpoint: str | Path,
    task,
    make_map: Callable[[], TransportMap] | None = None,
    steps: int | None = None,
    execute: int | None = None,
    pull_back: str = "agent",
    control_hz: float = 10.0,
    fit_on: str | list[str] = "all",
    search: SourceSearch | dict | None = None,
    reach: float | None = None,
    turn_deg: float | None = None,
    input_margin: float | None = INPUT_MARGIN,
    max_batch: int = 1,
    max_wait_ms: float = DEFAULT_MAX_WAIT_MS,
    solver: str | None = None,
    segments: bool = False,
    map_name: str | None = None,
) -> Deployment:
    """The K-CFM of ``checkpoint`` (a path, or ``release:NAME``: :mod:`kpflow.utils.releases`), trained on
    ``task`` (whose keypoint layout it must fit; None: a policy trained on
    data of no kpflow task, served with the keypoints and actions its checkpoint declares), ready to serve,
    transported online through maps from ``make_map`` (a factory of unfitted maps with an inverse: what ``map=``
    builds in kpflow-evaluate and kpflow-serve, ``map_name`` naming it in the metadata; the source index is read from
    beside the checkpoint) or as it is (None). Built by the one policy builder (:mod:`kpflow.policies.factory`):
    a transported one fits its map on ``fit_on`` (group or role names of the task's layout, or ``"all"``; with
    ``segments``, phase by phase as the task declares its phases) and
    finds its source as ``search`` says (:class:`~kpflow.policies.source_search.SourceSearch`, the options
    ``kpflow-evaluate`` takes: the saved index searched with its weights and frame; None: the saved index as it
    is, the nearest source). ``reach`` and ``turn_deg`` (planar tasks) show the policy its goal
    within that distance and turn of its object (:class:`~kpflow.policies.subgoal.SubgoalPolicy`). ``input_margin``:
    how far outside the K-CFM's training keypoints an observation may lie before it is refused, in extents of their
    box on each side (:meth:`~kpflow.policies.kcfm.KCFM.check_in_range`; None: no range check). ``max_batch`` (1: off)
    and ``max_wait_ms``: batch the network calls of policies acting at once (:class:`~kpflow.serving.batching.BatchedNetwork`;
    a batched reply equals the unbatched one up to floating-point effects of the batch size). ``steps`` and
    ``solver``, ``execute``, ``reach`` and ``turn_deg``: None takes the checkpoint's own settings
    (:mod:`kpflow.policies.settings`; ``reach``/``turn_deg`` False: the goal as observed).

    Raises ``FileNotFoundError`` for a missing checkpoint or source index and ``ValueError`` naming the problem for
    an unusable one (see :func:`~kpflow.utils.checkpoint.read_checkpoint`), a checkpoint of another task, an
    unknown keypoint group, a map factory that is not callable, a ``max_batch`` below 1 or a negative ``max_wait_ms``.
    """
    from ..maps.learned import check_map_factory
    from ..policies.factory import check_checkpoint_fits, fit_on_indices, layout_of, make_kcfm, make_transported_kcfm
    from ..policies.kcfm.model import KCFM
    from ..policies.kcfm.policy import check_steps_and_execute
    from ..utils.checkpoint import load_checkpoint
    from ..utils.releases import resolve_release

    check_batching(max_batch, max_wait_ms)
    checkpoint = resolve_release(checkpoint)  # its source index and digest are read beside it
    if make_map is not None and not callable(make_map):
        raise ValueError(f"make_map must be a factory of unfitted maps (e.g. kpflow.maps.ILWRMap) or None, got {type(make_map).__name__}")
    model = load_checkpoint(KCFM, checkpoint, map_location="cpu")
    execute = check_steps_and_execute(model, steps, execute, solver)
    hp = model.hparams
    if task is None:  # no task: the layout the checkpoint was trained with, without named groups
        layout = PolicyLayout(int(hp.n_keypoints), int(hp.keypoint_dim), int(hp.action_dim))
    else:
        check_checkpoint_fits(str(checkpoint), model.hparams, task)
        layout = layout_of(task)
    k, d, n_obs = int(hp.n_keypoints), int(hp.keypoint_dim), int(hp.n_obs)
    shown = model.settings.given(reach=reach, turn_deg=turn_deg)  # the checkpoint's limits unless given
    limits = {name: value for name, value in (("reach", shown.reach), ("turn_deg", shown.turn_deg)) if value is not None}
    if make_map is None:
        def make_policy() -> Policy:
            return make_kcfm(model, layout, steps, execute, input_margin, reach, turn_deg, solver)
        name = "kcfm"
    else:
        index = SourceIndex.load(source_index_path(checkpoint))
        if search is not None:
            search = SourceSearch.of(search)
            index = search.reindexed(index, layout)
        fit = fit_on_indices(layout, fit_on)
        check_map_factory(make_map, len(fit) if fit else layout.n_keypoints, layout.keypoint_dim, "the served transported K-CFM")

        def make_policy() -> Policy:
            return make_transported_kcfm(model, index, layout, make_map, steps, execute, pull_back, fit, input_margin, reach, turn_deg, solver,
                                         segments, search)  # fmt: skip
        name = f"transported_kcfm/{map_name or getattr(make_map, '__name__', type(make_map).__name__)}"
    network = None
    if max_batch > 1:
        network = model.ema_net = BatchedNetwork(model.ema_net, int(max_batch), float(max_wait_ms), trace=True)
        unbatched = make_policy

        def make_policy() -> Policy:
            return BatchedPolicy(unbatched(), network)
    make_policy()  # checks it all now
    name = "/".join([name, *(f"{limit}={float(value):g}" for limit, value in limits.items())])
    observation = {"keypoints": [k, d]} if n_obs == 1 else {"keypoints_history": [n_obs, k, d]}
    groups = {group: len(idx) for group, idx in layout.groups.items()} or {"keypoints": k}
    metadata = PolicyMetadata(
        policy=name, observation=observation, keypoint_groups=groups, action_shape=[int(execute), int(hp.action_dim)],
        horizon=int(hp.horizon), n_obs=n_obs, control_hz=float(control_hz), checkpoint_sha256=sha256(checkpoint),
    )  # fmt: skip
    return Deployment(make_policy, metadata, network)
