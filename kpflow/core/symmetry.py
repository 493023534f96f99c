"""A task's symmetries: relabellings of its keypoints that leave the task as it was, and which correspondence an
online transport takes among them.

A square peg turned by a quarter turn about its axis is the same peg, and a parallel-jaw gripper turned by a half
turn about its approach axis closes the same way; the keypoints do not say which of these labellings the source's
corresponds to. A :class:`Symmetry` is one such relabelling: observed keypoints ``T`` read as ``T' = T[perm]``
(keypoint ``i`` of ``T'`` is keypoint ``perm[i]`` of ``T``), and, for a turn of the tool itself (the jaws), the turn
``tool_turn`` (rad, about the tool's own z axis) by which a transported chunk's rotations ``R`` are turned,
``R -> R Rz(tool_turn)``: the robot is told to do what the K-CFM planned for the relabelled gripper with the
gripper it has. ``holding`` says when it holds (the jaws' half turn only while nothing is held; None: always).

The map of a phase is fitted ``phi_c(S[fit_on]) ~= T_c[fit_on]`` for each correspondence ``c`` of the phase
(:func:`phase_correspondences`: the identity, every symmetry that relabels a keypoint the phase is fitted on, and
the tool's own where the phase holds nothing); each yields another transported chunk, and an :class:`ArmLimits`
(the task's) rates how hard each is for the arm, ``inf`` where the arm cannot follow it (a joint past its range, a
target out of reach). :class:`~.transported_kcfm.TransportedKCFMPolicy` takes the cheapest at a phase's first
decision, keeps it while the arm can follow, and otherwise tries the others and then the next sources.

:func:`turn_permutation` builds an object's turn from its keypoints: the permutation that a rotation about a
vertical axis maps the keypoints onto.

This module imports nothing else of kpflow but :mod:`kpflow.geometry`: :mod:`.base` holds a layout's symmetries (and
checks that each relabels the layout's keypoints).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence, runtime_checkable

import numpy as np

from kpflow.geometry.angles import yaw_rotation


@dataclass(frozen=True)
class Symmetry:
    """One relabelling of the keypoints (module docstring): ``perm [K]`` (a permutation of ``0..K-1``), the tool's
    ``tool_turn`` (rad) and when it holds, ``holding``."""

    name: str
    perm: tuple[int, ...]
    tool_turn: float = 0.0
    holding: bool | None = None

    def __post_init__(self) -> None:
        if sorted(self.perm) != list(range(len(self.perm))):
            raise ValueError(
                f"symmetry {self.name!r}: perm must be a permutation of 0..{len(self.perm) - 1}, got {self.perm}"
            )
        if not np.isfinite(self.tool_turn):
            raise ValueError(f"symmetry {self.name!r}: tool_turn must be finite, got {self.tool_turn}")

    def moves(self) -> set[int]:
        """The keypoints it relabels."""
        return {i for i, j in enumerate(self.perm) if i != j}


def identity(k: int) -> Symmetry:
    """The relabelling that changes nothing, of ``k`` keypoints."""
    return Symmetry("identity", tuple(range(k)))


def phase_correspondences(
    symmetries: Sequence[Symmetry], k: int, fit_on: Sequence[int], holding: bool | None
) -> list[Symmetry]:
    """The correspondences a phase fitted on ``fit_on`` that holds (``holding``) chooses among: the identity first,
    then each symmetry that relabels a keypoint of ``fit_on`` or turns the tool, where it holds in the phase (a
    symmetry with ``holding`` set holds only in a phase with the same ``holding``); the identity alone without
    ``symmetries``."""
    fit = set(int(i) for i in fit_on)
    out = [identity(k)]
    for s in symmetries:
        if s.holding is not None and s.holding != holding:
            continue
        if s.tool_turn or s.moves() & fit:
            out.append(s)
    return out


def turn_permutation(keypoints: np.ndarray, axis: np.ndarray, angle: float, atol: float = 1e-6) -> tuple[int, ...]:
    """The permutation ``perm`` with ``keypoints[perm[i]] = R(angle) (keypoints[i] - axis) + axis`` (a turn by
    ``angle`` about the vertical through ``axis [3]``) for keypoints ``[N, 3]``; ``ValueError`` where the turn does
    not map the keypoints onto themselves."""
    p = np.asarray(keypoints, np.float64)
    turned = (p - axis) @ yaw_rotation(angle).T + axis
    dist = np.linalg.norm(turned[:, None] - p[None], axis=-1)
    perm = dist.argmin(1)
    if not np.all(dist[np.arange(len(p)), perm] < atol) or len(set(perm.tolist())) != len(p):
        raise ValueError(f"a turn by {angle:.3f} rad does not map these {len(p)} keypoints onto themselves")
    return tuple(int(j) for j in perm)


@runtime_checkable
class ArmLimits(Protocol):
    """How hard a chunk of actions is for the arm from where it is now: ``cost(obs, chunk [H, A])``, a finite number
    (lower is easier) or ``inf`` where the arm cannot follow it."""

    def cost(self, obs: dict, chunk: np.ndarray) -> float: ...
