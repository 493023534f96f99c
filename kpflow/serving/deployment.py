"""A checkpoint made ready to serve: a factory of independent policies and the metadata that describes them.

The server gives every connection its own policy from :attr:`Deployment.make_policy` (its own sampling noise and
last decision), all sharing one loaded model and, for a transported K-CFM, one source index. The source index of a
transporting policy lives beside its checkpoint as ``source_index.npz`` (:meth:`SourceIndex.save`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..data.source_index import SourceIndex
from ..maps import AffineMap, GPMap, ILWRMap
from ..policies.checks import INPUT_MARGIN
from ..tasks.base import Policy
from .protocol import PolicyMetadata

#: The maps a transported K-CFM can be served with (``transport=...``); each has an inverse.
TRANSPORT_MAPS: dict[str, Callable] = {"ilwr": ILWRMap, "gp": GPMap, "rigid": lambda: AffineMap(kind="rigid")}
SOURCE_INDEX_FILE = "source_index.npz"
PUSHT_KEYPOINTS = {"block": 12, "goal": 12, "agent": 1}


@dataclass(frozen=True)
class Deployment:
    """``make_policy()`` builds a fresh policy (``reset``/``act``) described by ``metadata``."""

    make_policy: Callable[[], Policy]
    metadata: PolicyMetadata


def sha256(path: str | Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def source_index_path(checkpoint: str | Path) -> Path:
    """Where a transporting policy's source index lives: ``source_index.npz`` beside the checkpoint."""
    return Path(checkpoint).parent / SOURCE_INDEX_FILE


def load_deployment(
    checkpoint: str | Path,
    transport: str | None = None,
    steps: int = 10,
    execute: int = 8,
    pull_back: str = "agent",
    control_hz: float = 10.0,
    keypoint_groups: dict[str, int] | None = None,
    fit_on: list[int] | None = None,
    choice: dict | None = None,
    reach: float | None = None,
    turn_deg: float | None = None,
    input_margin: float | None = INPUT_MARGIN,
) -> Deployment:
    """The K-CFM of ``checkpoint`` ready to serve, transported online through a ``transport`` map (``"ilwr"``,
    ``"gp"``, ``"rigid"``; the source index is read from beside the checkpoint) or as it is (None). A transported one
    fits its map on the keypoints ``fit_on`` (all when None) and chooses its source with the
    :class:`~kpflow.policies.source_choice.SourceChoice` options ``choice`` (the nearest, no stuck detection, when None).

    ``keypoint_groups`` names the observation's keypoints in order (Push-T's by default when the count fits).
    ``reach`` (px) and ``turn_deg`` (degrees; Push-T's keypoints only) show the policy, transported or not, its goal
    within that distance and turn of the block (:class:`~kpflow.policies.subgoal.SubgoalPolicy`). ``input_margin``:
    how far outside the K-CFM's training keypoints an observation may lie before it is refused, in extents of their
    box on each side (:meth:`~kpflow.policies.kcfm.KCFM.check_in_range`; None: no range check).

    Raises ``FileNotFoundError`` for a missing checkpoint or source index and ``ValueError`` naming the problem for
    an unusable one (see :func:`~kpflow.utils.checkpoint.read_checkpoint`), an unknown map or groups that do not
    add up to the model's keypoints.
    """
    from ..policies.kcfm import KCFM
    from ..policies.kcfm_policy import KCFMPolicy, check_steps_and_execute
    from ..policies.pusht_build import within_reach
    from ..policies.transported_kcfm import TransportedKCFMPolicy
    from ..utils.checkpoint import load_checkpoint

    if transport is not None and transport not in TRANSPORT_MAPS:
        raise ValueError(f"transport must be None or one of {sorted(TRANSPORT_MAPS)}, got {transport!r}")
    model = load_checkpoint(KCFM, checkpoint, map_location="cpu")
    check_steps_and_execute(model, steps, execute)
    hp = model.hparams
    k, d, n_obs = int(hp.n_keypoints), int(hp.keypoint_dim), int(hp.n_obs)
    if keypoint_groups is None:
        keypoint_groups = dict(PUSHT_KEYPOINTS) if k == sum(PUSHT_KEYPOINTS.values()) and d == 2 else {"keypoints": k}
    keypoint_groups = {str(name): int(n) for name, n in keypoint_groups.items()}
    if sum(keypoint_groups.values()) != k or min(keypoint_groups.values()) < 1:
        raise ValueError(f"keypoint_groups {keypoint_groups} must count the model's {k} keypoints, each group at least 1")
    limits = {name: value for name, value in (("reach", reach), ("turn_deg", turn_deg)) if value is not None}
    if limits and keypoint_groups != PUSHT_KEYPOINTS:
        raise ValueError(f"{' and '.join(limits)} apply to Push-T's keypoints {PUSHT_KEYPOINTS}; got keypoint_groups={keypoint_groups}")
    if transport is None:
        def make_policy() -> Policy:
            return within_reach(KCFMPolicy(model, steps, execute, input_margin), reach, turn_deg)
        name = "kcfm"
    else:
        index = SourceIndex.load(source_index_path(checkpoint))
        make_map = TRANSPORT_MAPS[transport]
        options = dict(choice or {})

        def make_policy() -> Policy:
            policy = TransportedKCFMPolicy(model, index, make_map, steps, execute, pull_back, fit_on, input_margin, **options)
            return within_reach(policy, reach, turn_deg)
        name = f"transported_kcfm/{transport}"
    make_policy()  # checks it all now
    name = "/".join([name, *(f"{limit}={float(value):g}" for limit, value in limits.items())])
    observation = {"keypoints": [k, d]} if n_obs == 1 else {"keypoints_history": [n_obs, k, d]}
    metadata = PolicyMetadata(
        policy=name, observation=observation, keypoint_groups=keypoint_groups, action_shape=[int(execute), int(hp.action_dim)],
        horizon=int(hp.horizon), n_obs=n_obs, control_hz=float(control_hz), checkpoint_sha256=sha256(checkpoint),
    )  # fmt: skip
    return Deployment(make_policy, metadata)
