"""What the policy server and its client say to each other (over :mod:`kpflow.serving.wire`).

On connect the server sends ``{"metadata": {...}}`` (:class:`PolicyMetadata`). Then each client message is a map
with exactly one key, and gets one reply:

- ``{"obs": {name: array}}`` -> ``{"actions": array [execute, A], "server_ms": float}``: the policy's ``act`` on
  the observation, whose names and shapes are the metadata's ``observation`` (finite numbers only);
- ``{"reset": {"seed": int | None}}`` -> ``{"reset": seed}``: the connection's policy starts a new episode.

Anything else, or an observation that does not fit, gets ``{"error": "<what was wrong>"}`` and the connection stays
open. Every connection has its own policy state (its sampling noise, its last decision).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

PROTOCOL_VERSION = 1
REQUESTS = ("obs", "reset")


@dataclass(frozen=True)
class PolicyMetadata:
    """What a client needs to drive the policy, sent on connect.

    Attributes:
        policy: what answers (``"kcfm"``, ``"transported_kcfm/ilwr"``, ...).
        observation: each observation key the policy reads and its shape (``{"keypoints": [25, 2]}``).
        keypoint_groups: the keypoints in order, by group and count (Push-T: block 12, goal 12, agent 1).
        action_shape: the shape of each reply's actions, ``[execute, action_dim]``.
        horizon: the length of the chunk the model samples (``execute`` of it are returned).
        n_obs: how many past observations the policy conditions on (``keypoints_history`` when more than 1).
        control_hz: the rate the actions are meant to be executed at.
        checkpoint_sha256: the SHA-256 of the checkpoint file served.
        protocol: this protocol's version.
    """

    policy: str
    observation: dict[str, list[int]]
    keypoint_groups: dict[str, int]
    action_shape: list[int]
    horizon: int
    n_obs: int
    control_hz: float
    checkpoint_sha256: str
    protocol: int = PROTOCOL_VERSION

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "PolicyMetadata":
        names = {f.name for f in fields(cls)}
        if not isinstance(data, dict) or (missing := {f.name for f in fields(cls) if f.name != "protocol"} - set(data)):
            raise ValueError(f"metadata is missing {sorted(missing) if isinstance(data, dict) else 'everything'}")
        return cls(**{k: v for k, v in data.items() if k in names})


def check_request(message: Any) -> tuple[str, Any]:
    """The request's kind (``"obs"`` or ``"reset"``) and body; ``ValueError`` naming what is wrong otherwise."""
    if not isinstance(message, dict):
        raise ValueError(f"a request must be a map with one key of {list(REQUESTS)}, got {type(message).__name__}")
    unknown = sorted(set(message) - set(REQUESTS))
    if unknown or len(message) != 1:
        raise ValueError(f"a request must have exactly one key of {list(REQUESTS)}, got {sorted(message)}")
    ((kind, body),) = message.items()
    return kind, body


def check_seed(body: Any) -> int | None:
    """The seed of a reset request's body ``{"seed": int | None}``."""
    if not isinstance(body, dict) or set(body) - {"seed"}:
        raise ValueError(f"reset takes {{'seed': int or None}}, got {body!r}")
    seed = body.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))):
        raise ValueError(f"reset's seed must be an integer or None, got {seed!r} ({type(seed).__name__})")
    return None if seed is None else int(seed)


def check_observation(obs: Any, spec: dict[str, list[int]]) -> dict[str, np.ndarray]:
    """``obs`` as float64 arrays if it has exactly ``spec``'s keys, each of its shape and finite; ``ValueError``
    naming the key and the problem otherwise."""
    if not isinstance(obs, dict):
        raise ValueError(f"obs must be a map of {sorted(spec)}, got {type(obs).__name__}")
    missing, unknown = sorted(set(spec) - set(obs)), sorted(set(obs) - set(spec))
    if missing or unknown:
        raise ValueError(f"obs must have exactly the keys {sorted(spec)}: missing {missing}, unknown {unknown}")
    out = {}
    for key, shape in spec.items():
        value = obs[key]
        if not isinstance(value, np.ndarray) or value.dtype.kind not in "iuf":
            raise ValueError(f"obs[{key!r}] must be a numeric array of shape {shape}, got {type(value).__name__}")
        if list(value.shape) != list(shape):
            raise ValueError(f"obs[{key!r}] must have shape {list(shape)}, got {list(value.shape)}")
        value = value.astype(np.float64)
        if not np.isfinite(value).all():
            raise ValueError(f"obs[{key!r}] holds {int((~np.isfinite(value)).sum())} NaN or inf value(s)")
        out[key] = value
    return out
