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
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from kpflow.core.policy import Policy

from ..policies.checks import INPUT_MARGIN
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
    task=None,
    overrides: Mapping | None = None,
    control_hz: float = 10.0,
    input_margin: float | None = INPUT_MARGIN,
    max_batch: int = 1,
    max_wait_ms: float = DEFAULT_MAX_WAIT_MS,
) -> Deployment:
    """The policy of ``checkpoint`` (a path, or ``release:NAME``: :mod:`kpflow.utils.releases`) ready to serve, built
    as its config says with ``overrides`` on top by the one builder (:class:`~kpflow.policies.factory.PolicyBuilder`:
    ``kind``, ``transport`` and the settings; a transported one reads its source index from beside the checkpoint),
    for ``task`` (whose keypoint layout it must fit; None: the layout the checkpoint records, or its bare shape).
    ``input_margin``: how far outside the K-CFM's training keypoints an observation may lie before it is refused
    (:meth:`~kpflow.policies.kcfm.KCFM.check_in_range`; None: no range check). ``max_batch`` (1: off) and
    ``max_wait_ms``: batch the network calls of policies acting at once (:class:`~kpflow.serving.batching.BatchedNetwork`;
    a batched reply equals the unbatched one up to floating-point effects of the batch size).

    Raises ``FileNotFoundError`` for a missing checkpoint or source index and ``ValueError`` naming the problem for
    an unusable one (see :func:`~kpflow.utils.checkpoint.read_checkpoint`), a checkpoint of another task, an option
    the policy ignores, an unknown keypoint group or map, a ``max_batch`` below 1 or a negative ``max_wait_ms``.
    """
    from ..policies.factory import PolicyBuilder

    check_batching(max_batch, max_wait_ms)
    builder = PolicyBuilder(checkpoint, overrides, task, None, input_margin)
    model, config, layout = builder.model, builder.config, builder.layout
    hp = model.hparams
    make_policy: Callable[[], Policy] = builder.build
    network = None
    if max_batch > 1:
        builder.build()  # the policy the builder checked was built on the unbatched network: never served
        network = model.ema_net = BatchedNetwork(model.ema_net, int(max_batch), float(max_wait_ms), trace=True)
        unbatched = make_policy

        def make_policy() -> Policy:
            return BatchedPolicy(unbatched(), network)

    probe = make_policy()  # checks it all now
    name = (
        config.kind
        if config.transport is None
        else f"{config.kind}/{config.transport.map}" + ("/segments" if config.transport.segments else "")
    )
    limits = {
        n: v
        for n, v in (("reach", config.settings.reach), ("turn_deg", config.settings.turn_deg))
        if v not in (None, False)
    }
    name = "/".join([name, *(f"{limit}={float(value):g}" for limit, value in limits.items())])
    k, d, n_obs = int(hp.n_keypoints), int(hp.keypoint_dim), int(hp.n_obs)
    observation = {"keypoints": [k, d]} if n_obs == 1 else {"keypoints_history": [n_obs, k, d]}
    groups = {group: len(idx) for group, idx in layout.groups.items()} or {"keypoints": k}
    metadata = PolicyMetadata(
        policy=name, observation=observation, keypoint_groups=groups, action_shape=[int(probe.execute), int(hp.action_dim)],
        horizon=int(hp.horizon), n_obs=n_obs, control_hz=float(control_hz), checkpoint_sha256=sha256(builder.checkpoint),
    )  # fmt: skip
    return Deployment(make_policy, metadata, network)
