"""Old command-line spellings, read as what they now say, with a note: the source search was a config group of its
own (``source_search=pusht``, ``source_search.<key>=<value>``); it is the policy's option now (``policy.search``,
``policy.transport.search`` for a transported K-CFM), its defaults the task's (Push-T: a stuck block detected).

* ``source_search.<key>=<value>`` -> ``++policy.search.<key>=<value>`` (``++policy.transport.search.<key>`` with
  ``policy=transported_kcfm``);
* ``source_search=pusht`` -> nothing (the Push-T task's own search); ``source_search=default`` ->
  ``++policy.search.stuck_decisions=false`` (no stuck detection).

Hydra would refuse these before the command starts, so they are rewritten in ``sys.argv`` first. ``split=`` (Push-T's
word for the condition) is read as ``condition=`` once the config is composed (:func:`read_split`).
"""

from __future__ import annotations

import functools
import logging
import sys
from typing import Callable, TypeVar

from omegaconf import DictConfig, open_dict

F = TypeVar("F", bound=Callable)
log = logging.getLogger(__name__)
OLD_GROUP = "source_search"


def new_spelling(args: list[str], renamed: dict[str, str] | None = None) -> tuple[list[str], list[str]]:
    """``(args, notes)``: the command-line ``args`` with the old spellings of the module docstring rewritten (and a
    command's own ``renamed`` keys: old -> new), and one note per rewritten argument."""
    renamed = renamed or {}
    transported = any(a in ("policy=transported_kcfm", "+policy=transported_kcfm") for a in args)
    node = "policy.transport.search" if transported else "policy.search"
    out, notes = [], []
    for arg in args:
        key, eq, value = arg.partition("=")
        bare = key.lstrip("+~")
        if eq and bare in renamed:
            new = f"{renamed[bare]}={value}"
            notes.append(f"{arg} is the old spelling of {new}: read as that")
            out.append(new)
            continue
        if not eq or not (bare == OLD_GROUP or bare.startswith(f"{OLD_GROUP}.")):
            out.append(arg)
            continue
        if bare == OLD_GROUP:
            if value == "pusht":
                notes.append(f"{arg}: the search is the task's own now (Push-T detects a stuck block); dropped")
                continue
            if value == "default":
                new = f"++{node}.stuck_decisions=false"
            else:
                raise SystemExit(
                    f"error: {arg}: the source_search group is gone; give the options as {node}={{candidates: 5, ...}}"
                )
        else:
            new = f"++{node}{bare[len(OLD_GROUP) :]}={value}"
        notes.append(f"{arg} is the old spelling of {new}: read as that")
        out.append(new)
    return out, notes


def old_spellings_read(main: F | None = None, *, renamed: dict[str, str] | None = None):
    """Wrap a command's entry point (outside ``hydra.main``) so that the old spellings in ``sys.argv`` are read as
    the new ones, each with a note on stderr: ``@old_spellings_read``, or ``@old_spellings_read(renamed={old: new})``
    for a command's own renamed keys."""
    if main is None:
        return functools.partial(old_spellings_read, renamed=renamed)

    @functools.wraps(main)
    def wrapper(*args, **kwargs):
        sys.argv[1:], notes = new_spelling(sys.argv[1:], renamed)
        for note in notes:
            print(f"note: {note}", file=sys.stderr, flush=True)
        return main(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


def read_split(cfg: DictConfig) -> None:
    """``split=`` (the old spelling of ``condition=``) read as ``condition``, with a note; both given and different:
    ``ValueError`` naming them. ``condition``'s default (``all`` or null) gives way to ``split``."""
    split = cfg.get("split")
    if split is None:
        return
    if cfg.get("condition") not in ("all", None, split):
        raise ValueError(
            f"split={split} (the old spelling of condition) contradicts condition={cfg.condition}: give condition alone"
        )
    log.warning("split=%s is the old spelling of condition=%s: read as that", split, split)
    with open_dict(cfg):
        cfg.condition, cfg.split = split, None
