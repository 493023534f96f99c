"""Typed checks of an entry point's config keys, run before anything is built or written.

Hydra passes ``n_configs=abc`` on as the string ``"abc"``, and the error would surface deep inside (a TypeError in
a range, Lightning's bare AssertionError). Each entry point declares its scalar keys as :class:`Key` specs and
:func:`check_config` refuses a wrong type or range with an error that names the key, the expected value and the
given one. :meth:`Key.check` does the same for a function's arguments.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any, Mapping

from omegaconf import DictConfig, OmegaConf

_ABSENT = object()


@dataclass(frozen=True)
class Key:
    """One scalar config key: its type (``int``, ``float``, ``bool`` or ``str``), optional lower and upper bounds,
    the allowed choices, and whether ``null`` is allowed. A number must be finite (``inf`` and ``nan`` are refused)."""

    kind: type
    lo: float | None = None
    choices: tuple | None = None
    nullable: bool = False
    hi: float | None = None

    def describe(self) -> str:
        what = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}[self.kind]
        if self.lo is not None and self.hi is not None:
            what += f" in {self.lo}..{self.hi}"
        elif self.lo is not None:
            what += f" >= {self.lo}"
        elif self.hi is not None:
            what += f" <= {self.hi}"
        if self.kind is float:
            what = "a finite " + what.removeprefix("a ")
        if self.choices is not None:
            what = "one of " + ", ".join(map(str, self.choices))
        return what + (" or null" if self.nullable else "")

    def accepts(self, value: Any) -> bool:
        if value is None:
            return self.nullable
        if self.kind is bool:
            ok = isinstance(value, bool)
        elif self.kind is int:
            ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
        elif self.kind is float:
            ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
        else:
            ok = isinstance(value, self.kind)
        if ok and self.lo is not None:
            ok = value >= self.lo
        if ok and self.hi is not None:
            ok = value <= self.hi
        if ok and self.choices is not None:
            ok = value in self.choices
        return ok

    def check(self, name: str, value: Any) -> Any:
        """``value`` if :meth:`accepts` it, else ``ValueError``: ``<name> must be <describe()>; got <value> (<type>)``."""
        if not self.accepts(value):
            raise ValueError(f"{name} must be {self.describe()}; got {value!r} ({type(value).__name__})")
        return value


def check_config(cfg: DictConfig, keys: Mapping[str, Key]) -> None:
    """Raise ``ValueError`` for the first dotted key of ``keys`` present in ``cfg`` whose value ``keys`` refuses
    (absent keys are skipped: e.g. a trainer config without ``max_steps``)."""
    for name, key in keys.items():
        value = OmegaConf.select(cfg, name, default=_ABSENT, throw_on_missing=False)
        if value is _ABSENT:
            continue
        key.check(f"config key {name}", value)


#: Every command's ``seed``: numpy's legacy generator and Lightning's ``seed_everything`` take 0..2**32 - 1, and
#: seeds are offset by a few thousand in places (a task's source scenes), so the bound keeps clear of the top.
SEED = Key(int, lo=0, hi=2**31 - 1)
#: A policy's ``reset(seed)``: an integer (numpy's too) or None; 1.5 is refused, not truncated.
RESET_SEED = Key(int, lo=0, nullable=True)

# Keys of Lightning's Trainer that kpflow's trainer configs set or users commonly override.
TRAINER_KEYS = {
    "trainer.max_epochs": Key(int, lo=-1, nullable=True),
    "trainer.min_epochs": Key(int, lo=0, nullable=True),
    "trainer.max_steps": Key(int, lo=-1),
    "trainer.check_val_every_n_epoch": Key(int, lo=1, nullable=True),
    "trainer.log_every_n_steps": Key(int, lo=1, nullable=True),
    "trainer.accumulate_grad_batches": Key(int, lo=1),
    "trainer.gradient_clip_val": Key(float, lo=0, nullable=True),
    "trainer.enable_progress_bar": Key(bool, nullable=True),
    "trainer.enable_checkpointing": Key(bool, nullable=True),
    "trainer.num_sanity_val_steps": Key(int, lo=-1, nullable=True),
}
