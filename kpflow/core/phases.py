"""A task's phases, read from what the robot observes: which keypoints an online transport follows in each.

Where two objects move independently (a cube to pick and the cube to stack it on), one map over all their keypoints
must stretch or fold the space between them. A skill is carried segment by segment instead, each in the frame of
the object that matters then (MimicGen's source segments, the paper's per-segment keypoints): before the grasp the
object to pick, after it the target, with the held object carried by the gripper. A task declares its phases
(:class:`Phases`, in its :class:`~kpflow.core.policy.PolicyLayout`); a transporting policy reads the phase of each
observation, and of each demonstrated configuration it may choose as a source, with the same rule:

* :class:`Grip` tells from the keypoints alone whether the jaws hold the object: the finger pads closer together
  than ``closed_below`` (and farther than ``empty_below``: closed on nothing) and the object's grasp segment (from
  the mean ``a`` of its ``grasp_from`` keypoints to the mean ``b`` of its ``grasp_to`` ones: a square nut's handle,
  a can's axis; a point where both are the same, a cube's centre) within ``reach`` of the pads' midpoint ``m``,
  ``holding(K) = empty_below < |p_1 - p_2| < closed_below  and  min_{s in [0, 1]} |a + s (b - a) - m| < reach``;
  nothing of the simulator's task state is read.
* :class:`Phase` names, by keypoint group or role, what the map is fitted on (``fit_on``), relative to which
  keypoints the source is searched (``frame``) with which weights (``weights``), and which keypoints are pulled back
  with the robot (``carried``: the held object); ``holding`` says when it applies (True: while the object is held,
  False: while it is not, None: always).

This module imports nothing else of kpflow: :mod:`.base` holds a layout's phases.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np


@dataclass(frozen=True)
class Grip:
    """Whether the jaws hold the object, from keypoints (module docstring): ``pads`` (the two finger pads' keypoint
    indices), ``grasp_from`` and ``grasp_to`` (the indices whose means end the segment the jaws close on),
    ``closed_below``, ``empty_below`` and ``reach`` (m, or the keypoints' unit)."""

    pads: tuple[int, int]
    grasp_from: tuple[int, ...]
    grasp_to: tuple[int, ...]
    closed_below: float
    empty_below: float
    reach: float

    def __post_init__(self) -> None:
        if len(self.pads) != 2 or len(set(self.pads)) != 2 or not self.grasp_from or not self.grasp_to:
            raise ValueError(
                f"a grip needs two distinct pad keypoints and grasp keypoints at both ends; got {self.pads}, {self.grasp_from}, {self.grasp_to}"
            )
        if not (0 <= self.empty_below < self.closed_below and self.reach > 0):
            raise ValueError(
                f"need 0 <= empty_below < closed_below and reach > 0; got {self.empty_below}, {self.closed_below}, {self.reach}"
            )

    def holding(self, keypoints: np.ndarray) -> np.ndarray:
        """``holding(K)`` for keypoint sets ``[..., K, D]``: a bool array ``[...]``."""
        keypoints = np.asarray(keypoints, np.float64)
        a, b = keypoints[..., self.pads[0], :], keypoints[..., self.pads[1], :]
        gap = np.linalg.norm(a - b, axis=-1)
        start = keypoints[..., list(self.grasp_from), :].mean(-2)
        along = keypoints[..., list(self.grasp_to), :].mean(-2) - start
        mid = (a + b) / 2
        s = np.clip(((mid - start) * along).sum(-1) / np.maximum((along * along).sum(-1), 1e-12), 0.0, 1.0)
        near = np.linalg.norm(start + s[..., None] * along - mid, axis=-1) < self.reach
        return (gap > self.empty_below) & (gap < self.closed_below) & near

    @property
    def keypoints(self) -> tuple[int, ...]:
        """Every keypoint index the grip reads."""
        return (*self.pads, *self.grasp_from, *self.grasp_to)


@dataclass(frozen=True)
class Phase:
    """One phase (module docstring); group and role names are the layout's."""

    name: str
    fit_on: tuple[str, ...]
    frame: tuple[str, ...]
    weights: Mapping[str, float] = field(default_factory=dict)
    carried: tuple[str, ...] = ()
    holding: bool | None = None

    def names(self) -> set[str]:
        """Every group or role name the phase uses."""
        return {*self.fit_on, *self.frame, *self.weights, *self.carried}


@dataclass(frozen=True)
class Phases:
    """A task's phases and the :class:`Grip` that tells them apart; :meth:`of` is the phase of a keypoint set."""

    grip: Grip
    phases: tuple[Phase, ...]

    def __post_init__(self) -> None:
        names = [p.name for p in self.phases]
        if not names or len(set(names)) != len(names):
            raise ValueError(f"phases need distinct names; got {names}")
        for held in (False, True):
            matching = [p.name for p in self.phases if p.holding in (held, None)]
            if len(matching) != 1:
                state = "held" if held else "not held"
                raise ValueError(f"exactly one phase must apply while the object is {state}; {matching or 'none'} do")

    def index(self, keypoints: np.ndarray) -> np.ndarray:
        """The phase of each keypoint set ``[..., K, D]`` as an index into :attr:`phases` (int array ``[...]``)."""
        free, held = (
            next(i for i, p in enumerate(self.phases) if p.holding in (state, None)) for state in (False, True)
        )
        return np.where(self.grip.holding(keypoints), held, free)

    def of(self, keypoints: np.ndarray) -> Phase:
        """The phase of one keypoint set ``[K, D]``."""
        return self.phases[int(self.index(np.asarray(keypoints)[None])[0])]
