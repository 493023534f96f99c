"""The robosuite tasks' object kinds, one file each (:mod:`.base`: what a kind declares), and their registry.

:data:`KINDS` maps a kind's name (what a :class:`~kpflow.tasks.suite.specs.TaskSpec` names in ``kinds``) to it;
:func:`object_kind` looks one up, naming the known ones for an unknown name; :data:`SYMMETRY` is each kind's number
of turns about the vertical that leave it unchanged (0: any).
"""

from .base import ObjectKind, reduced_yaw
from .bin import BIN
from .can import CAN
from .cube import CUBE
from .nut import NUT, NUT_HANDLE_KIND, NUT_RING
from .peg import PEG

KINDS: dict[str, ObjectKind] = {k.name: k for k in (CUBE, CAN, NUT, NUT_HANDLE_KIND, NUT_RING, PEG, BIN)}
SYMMETRY = {name: kind.symmetry for name, kind in KINDS.items()}  # turns that leave it unchanged (0: any)


def object_kind(name: str) -> ObjectKind:
    """The kind called ``name``; ``ValueError`` naming the known ones for another."""
    kind = KINDS.get(name)
    if kind is None:
        raise ValueError(f"unknown keypoint kind {name!r}; choose one of {sorted(KINDS)}")
    return kind


__all__ = ["KINDS", "SYMMETRY", "ObjectKind", "object_kind", "reduced_yaw"]
