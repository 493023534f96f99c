"""A policy's own settings, saved in its checkpoint: loading it with no overrides acts as its results page measured.

A K-CFM's figures depend on more than its weights: how many network calls sample a chunk (``steps``) and with which
``solver``, how many of the chunk's actions run (``execute``), and, on a planar task with a goal, how far from its
object the goal is shown (``reach``, ``turn_deg``: :mod:`.subgoal`). :class:`PolicySettings` holds them (LeRobot's
pattern: one config record per policy) and is written into the checkpoint as a plain record under
:data:`CHECKPOINT_KEY` by ``kpflow-release settings.<name>=<value>``; :meth:`KCFM.on_load_checkpoint
<kpflow.policies.kcfm.KCFM.on_load_checkpoint>` reads it back.

Which value a policy uses, first found wins: the one given (a config key, a ``make_*`` argument), the checkpoint's
record, the model's own (``sampler.steps``, ``sampler.solver``) or the built-in default (8 actions, the goal as observed).
``reach=False`` / ``turn_deg=False`` ask for the goal as observed even where the checkpoint records a limit.
:func:`effective_settings` reads back from a built policy what it uses, for the run's ``config.yaml``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any, Mapping

from kpflow.maps.validation import check_positive
from kpflow.utils.config_checks import Key

#: The checkpoint's key of the record (beside ``state_dict`` and ``hyper_parameters``).
CHECKPOINT_KEY = "policy_settings"

#: Each setting's type and range (``steps``' upper bound is :data:`kpflow.policies.kcfm.MAX_STEPS`).
KEYS = {
    "steps": Key(int, lo=1, hi=100, nullable=True),
    "solver": Key(str, nullable=True),
    "execute": Key(int, lo=1, nullable=True),
    "reach": Key(float, nullable=True),  # and > 0 (check_positive, the message SubgoalPolicy gives)
    "turn_deg": Key(float, nullable=True),
}
EXECUTE = 8  # actions of a chunk run when neither the config nor the checkpoint says


@dataclass(frozen=True)
class PolicySettings:
    """What a policy acts with besides its weights (module docstring); None: not set here."""

    steps: int | None = None
    solver: str | None = None
    execute: int | None = None
    reach: float | None = None
    turn_deg: float | None = None

    def __post_init__(self) -> None:
        for name, key in KEYS.items():
            key.check(name, getattr(self, name))
        check_positive("reach", self.reach, optional=True, what=" (the largest object-goal distance shown)")
        check_positive("turn_deg", self.turn_deg, optional=True, what=" (the largest object-goal turn shown, degrees)")

    @classmethod
    def from_record(cls, record: Any, where: str = "the checkpoint") -> PolicySettings:
        """The settings of a checkpoint's record (None or absent: none set). ``ValueError`` naming ``where`` and the
        key for a record that is not a mapping, names an unknown setting or holds a value out of range."""
        if record is None:
            return cls()
        if not isinstance(record, Mapping):
            raise ValueError(f"{where}: {CHECKPOINT_KEY!r} must be a mapping of settings, got {type(record).__name__}")
        try:
            return cls().given(**{str(k): v for k, v in record.items()})
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None

    def record(self) -> dict:
        """The settings that are set, as a plain record (what the checkpoint stores)."""
        return {k: v for k, v in asdict(self).items() if v is not None}

    def given(self, **values) -> PolicySettings:
        """These settings with ``values`` (config keys, arguments) on top: None keeps this record's value, and
        ``False`` for ``reach``/``turn_deg`` clears it (the goal as observed)."""
        if unknown := sorted(set(values) - set(KEYS)):
            raise ValueError(f"{CHECKPOINT_KEY!r} names unknown setting(s) {unknown}; known: {sorted(KEYS)}")
        changed = {}
        for name, value in values.items():
            if value is False and name in ("reach", "turn_deg"):
                changed[name] = None
            elif value is not None:
                changed[name] = value  # checked by the constructor
        return replace(self, **changed)

    @property
    def actions(self) -> int:
        """How many actions of a chunk run (:data:`EXECUTE` when not set)."""
        return EXECUTE if self.execute is None else self.execute


def effective_settings(policy) -> dict:
    """What a built policy acts with (``steps``, ``solver``, ``execute``, ``reach``, ``turn_deg``), read down its
    wrappers (each holding the next as ``policy``); settings no layer has are left out."""
    found: dict = {}
    layer, seen = policy, set()
    while layer is not None and id(layer) not in seen:
        seen.add(id(layer))
        for name in KEYS:
            if name not in found and hasattr(layer, name):
                found[name] = getattr(layer, name)
        layer = getattr(layer, "policy", None)
    return found
