"""The policy contract: what a policy declares, what it observes, and the one closed loop that runs it.

* :class:`Policy`: ``reset(seed)`` and ``act(obs) -> [H, A]`` (an action chunk), with its observation history
  ``n_obs`` and the number of actions it means to be executed, ``execute``.
* :class:`PolicyLayout`: what a task shows its learned policies and takes back: ``n_keypoints`` keypoints in
  ``keypoint_dim``-D, named keypoint ``groups`` with their roles (``objects``, ``goals``, ``robot``), and actions of
  ``action_dim`` values whose first ``keypoint_dim`` are a position in the keypoints' space, followed by a 6-D
  rotation (:mod:`kpflow.geometry.rotations`) when ``rotation`` is set; the rest (a gripper) is not spatial. A task declares
  it (``task.policy_layout``); transporting policies read from it what a map moves and what it leaves alone, and,
  where the task declares them, its ``phases`` (:mod:`.phases`: which object the transport follows before and after
  a grasp) and its ``symmetries`` (:mod:`.symmetry`: the relabellings of its keypoints that leave the task as it
  was, a square peg's quarter turns, the jaws' half turn).
* :class:`ClosedLoop`: a policy at 1 action per control step. It owns the observation history (the last ``n_obs``
  keypoint sets, oldest first, the episode's first repeated before its start, as training pads) and the action
  queue (a chunk is executed open loop; the policy is asked again when it runs out). Every task's episode loop
  (Push-T's and the robosuite tasks') runs its policy through it.

This module imports nothing else of kpflow but :mod:`.phases` and :mod:`.symmetry` (which import only
:mod:`kpflow.geometry`): tasks import it to declare their layout.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any, Mapping, Protocol, runtime_checkable

import numpy as np

from kpflow.core.phases import Grip, Phase, Phases
from kpflow.core.symmetry import Symmetry

ROLES = ("objects", "goals", "robot")


@runtime_checkable
class Policy(Protocol):
    """A closed-loop policy: ``reset(seed)`` and ``act(obs) -> action chunk [H, A]``. ``n_obs`` (observation
    frames it conditions on; 1 when absent) and ``execute`` (actions of a chunk meant to be executed) are declared
    by the policies that have them."""

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode (``seed`` makes stochastic policies reproducible)."""

    def act(self, obs: dict) -> np.ndarray:
        """An action chunk ``[H, A]`` for the observation; the caller executes it and asks again."""


@dataclass(frozen=True)
class PolicyLayout:
    """What a task's learned policies observe and return (module docstring).

    ``groups`` maps a group name to its keypoint indices (Push-T: ``block``, ``goal``, ``agent``); ``roles`` maps each
    of :data:`ROLES` to the names of its groups. A name in a policy's options (weights, the frame searched in, the
    keypoints a map is fitted on) is a group's or a role's. ``transport``: the task's defaults for transporting
    policies, plain options of :class:`~kpflow.policies.config.TransportConfig` (Push-T: the map fitted on the
    block and the agent, a stuck block detected; the robosuite tasks: phase by phase).

    :meth:`record` is the layout as plain data (what a checkpoint stores beside the weights) and :meth:`from_record`
    reads it back.
    """

    n_keypoints: int
    keypoint_dim: int
    action_dim: int
    groups: Mapping[str, tuple[int, ...]] = field(default_factory=dict, compare=False)
    roles: Mapping[str, tuple[str, ...]] = field(default_factory=dict, compare=False)
    rotation: bool = field(default=False, compare=False)
    phases: Phases | None = field(default=None, compare=False)
    symmetries: tuple[Symmetry, ...] = field(default=(), compare=False)
    transport: Mapping[str, Any] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        seen = sorted(i for idx in self.groups.values() for i in idx)
        if self.groups and seen != list(range(self.n_keypoints)):
            raise ValueError(
                f"the groups {dict(self.groups)} must name each of the {self.n_keypoints} keypoints exactly once"
            )
        for role, names in self.roles.items():
            if role not in ROLES or any(n not in self.groups for n in names):
                raise ValueError(
                    f"role {role!r} -> {names}: roles are {ROLES} and name groups of {sorted(self.groups)}"
                )
        spatial = self.keypoint_dim + (6 if self.rotation else 0)
        if self.action_dim < self.keypoint_dim or spatial > self.action_dim:
            raise ValueError(f"actions of {self.action_dim} values cannot start with a {self.keypoint_dim}-D position"
                             + (" and a 6-D rotation" if self.rotation else ""))  # fmt: skip
        if self.phases is not None:
            grip = self.phases.grip
            if not all(0 <= i < self.n_keypoints for i in grip.keypoints):
                raise ValueError(f"the grip's keypoints {grip.keypoints} must be in 0..{self.n_keypoints - 1}")
            for phase in self.phases.phases:
                for name in phase.names():
                    self.indices(name)  # raises naming an unknown group
        for symmetry in self.symmetries:
            if len(symmetry.perm) != self.n_keypoints:
                raise ValueError(
                    f"symmetry {symmetry.name!r} relabels {len(symmetry.perm)} keypoints; the layout has {self.n_keypoints}"
                )

    def record(self) -> dict:
        """The layout as plain data: strings, numbers, lists and mappings (:meth:`from_record` reads it back)."""

        def plain(value):
            if isinstance(value, Mapping):
                return {str(k): plain(v) for k, v in value.items()}
            if isinstance(value, (tuple, list)):
                return [plain(v) for v in value]
            if hasattr(value, "__dataclass_fields__"):
                return {f: plain(getattr(value, f)) for f in value.__dataclass_fields__}
            return value.item() if isinstance(value, np.generic) else value

        return plain(self)

    @classmethod
    def from_record(cls, record: Mapping, where: str = "the checkpoint") -> PolicyLayout:
        """The layout of a :meth:`record`; ``ValueError`` naming ``where`` for a record that is not one."""
        try:
            r = dict(record)
            phases = r.get("phases")
            if phases is not None:
                grip = {k: tuple(v) if isinstance(v, list) else v for k, v in phases["grip"].items()}
                phases = Phases(
                    Grip(**grip),
                    tuple(
                        Phase(**{k: tuple(v) if isinstance(v, list) else v for k, v in p.items()})
                        for p in phases["phases"]
                    ),
                )
            return cls(
                int(r["n_keypoints"]), int(r["keypoint_dim"]), int(r["action_dim"]),
                {str(k): tuple(int(i) for i in v) for k, v in r.get("groups", {}).items()},
                {str(k): tuple(str(n) for n in v) for k, v in r.get("roles", {}).items()},
                bool(r.get("rotation", False)), phases,
                tuple(Symmetry(s["name"], tuple(s["perm"]), float(s.get("tool_turn", 0.0)), s.get("holding")) for s in r.get("symmetries", [])),
                dict(r.get("transport", {})),
            )  # fmt: skip
        except (KeyError, TypeError, AttributeError) as e:
            raise ValueError(f"{where}: its keypoint layout record is malformed ({type(e).__name__}: {e})") from None

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(n_keypoints, keypoint_dim, action_dim)``: what a checkpoint must match."""
        return self.n_keypoints, self.keypoint_dim, self.action_dim

    def indices(self, *names: str) -> tuple[int, ...]:
        """The keypoint indices of the groups or roles ``names`` (in keypoint order; ``"all"``: every keypoint)."""
        if "all" in names:
            return tuple(range(self.n_keypoints))
        out: set[int] = set()
        for name in names:
            if name in self.groups:
                out.update(self.groups[name])
            elif name in self.roles:
                out.update(i for g in self.roles[name] for i in self.groups[g])
            else:
                raise ValueError(
                    f"unknown keypoint group {name!r}; this task's groups are {sorted(self.groups)} and roles {sorted(self.roles)}"
                )
        return tuple(sorted(out))

    def weights(self, weights: Mapping[str, float] | None) -> np.ndarray:
        """Per-keypoint weights ``[K]`` from weights per group or role (1 where none is given)."""
        out = np.ones(self.n_keypoints, np.float32)
        for name, w in (weights or {}).items():
            if not (np.isfinite(w) and w >= 0):
                raise ValueError(f"keypoint weight {name} must be finite and >= 0, got {w}")
            out[list(self.indices(name))] = w
        return out


class ClosedLoop:
    """``policy`` run one action per control step (module docstring): :meth:`observe` every step, :meth:`action` when
    the policy acts, :meth:`drop` to discard the pending chunk (another controller took over)."""

    def __init__(self, policy: Policy, action_dim: int | None = None) -> None:
        self.policy, self.action_dim = policy, action_dim
        self.n_obs = int(getattr(policy, "n_obs", 1))
        self.reset()

    def reset(self, seed: int | None = None, policy: bool = True) -> None:
        """Forget the history and the queue; reset the policy with ``seed`` too when ``policy``."""
        if policy:
            self.policy.reset(seed)
        self.history: deque = deque(maxlen=self.n_obs)
        self.queue: deque = deque()
        self.decisions = 0

    def observe(self, obs: dict) -> None:
        """Record this step's keypoints (the first repeated to fill the history)."""
        keypoints = obs["keypoints"]
        self.history.extend([keypoints] * (self.n_obs if not self.history else 1))

    def action(self, obs: dict) -> np.ndarray:
        """The next action ``[A]``: the head of the queue, asking the policy for a chunk when it is empty (with
        ``obs["keypoints_history"] [n_obs, K, D]`` added for a policy with an observation history)."""
        if not self.queue:
            seen = dict(obs, keypoints_history=np.stack(self.history)) if self.n_obs > 1 else obs
            chunk = np.atleast_2d(np.asarray(self.policy.act(seen), dtype=np.float64))
            if self.action_dim is not None and (
                chunk.ndim != 2 or chunk.shape[1] != self.action_dim or not np.isfinite(chunk).all()
            ):
                raise ValueError(f"the policy must return finite chunks [H, {self.action_dim}]; got {chunk.shape}")
            self.queue.extend(chunk)
            self.decisions += 1
        return self.queue.popleft()

    def reads_next(self) -> bool:
        """Whether the next observation will be in the history of a decision: the queue holds fewer actions than
        the history's length (so the steps left before the next decision all feed it)."""
        return len(self.queue) < self.n_obs

    def drop(self) -> None:
        self.queue.clear()
