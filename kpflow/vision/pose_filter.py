"""Object poses filtered over camera reads, so that one noisy read does not move a grasp.

Each read of a still object is its true pose plus the sensor's error; a policy that reads the cameras at every
decision sees the object jump by a few millimetres from one decision to the next, which is enough to lose a square
nut's handle. :class:`PoseFilter` keeps, per object, the reads that agree with its estimate and reports

* the position: the component-wise median of the last ``window`` accepted reads' positions;
* the yaw: their circular mean, each read first turned by the multiple of ``2 pi / order`` nearest the estimate
  (``order``: the turns that leave the object unchanged, 0 for a yaw that does not exist, as a can's);
* for a cube, its half side: the median of the accepted reads'.

A read farther than ``gate`` (m) or ``gate_deg`` from the estimate is an outlier and is not used; ``patience``
outliers in a row mean the object moved (nudged by the jaws, set down elsewhere), and the filter starts again from
those reads. :meth:`PoseFilter.forget` drops an object (released by the jaws: it is where it was put now).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FilteredPose:
    """A filtered pose: ``pos [3]``, ``yaw`` (rad) and a cube's ``half`` side (None for other objects)."""

    pos: np.ndarray
    yaw: float
    half: float | None = None


class PoseFilter:
    """Per-object median filter with outlier rejection over reads (module docstring).

    Args:
        window: how many accepted reads the estimate is the median of (>= 1; 1: the last accepted read).
        gate: a read whose position is farther than this (m) from the estimate is an outlier.
        gate_deg: a read whose yaw is farther than this (degrees, modulo the object's symmetry) is an outlier.
        patience: after this many outliers in a row the object is taken to have moved (>= 1).
    """

    def __init__(self, window: int = 5, gate: float = 0.02, gate_deg: float = 20.0, patience: int = 2) -> None:
        if int(window) != window or window < 1 or int(patience) != patience or patience < 1:
            raise ValueError(f"window and patience must be whole numbers >= 1; got {window!r}, {patience!r}")
        if not (np.isfinite(gate) and gate > 0 and np.isfinite(gate_deg) and gate_deg > 0):
            raise ValueError(f"gate (m) and gate_deg must be positive numbers; got {gate!r}, {gate_deg!r}")
        self.window, self.patience = int(window), int(patience)
        self.gate, self.gate_rad = float(gate), float(np.radians(gate_deg))
        self.reset()

    def reset(self) -> None:
        """Forget every object (a new scene)."""
        self.reads: dict[str, deque] = {}
        self.outliers: dict[str, list] = {}
        self.estimate: dict[str, FilteredPose] = {}

    def forget(self, name: str) -> None:
        """Forget object ``name`` (it was moved on purpose)."""
        for store in (self.reads, self.outliers, self.estimate):
            store.pop(name, None)

    def update(self, name: str, pos: np.ndarray, yaw: float, order: int, half: float | None = None) -> FilteredPose:
        """Add a read of object ``name`` (``pos [3]``, ``yaw``, the symmetry ``order``, a cube's ``half``) and return
        its filtered pose."""
        read = FilteredPose(np.asarray(pos, float).copy(), float(yaw), half)
        old = self.estimate.get(name)
        if old is not None and not self._agrees(old, read, order):
            self.outliers.setdefault(name, []).append(read)
            if len(self.outliers[name]) < self.patience:
                return old
            moved = self.outliers.pop(name)
            self.reads[name] = deque(moved, maxlen=self.window)  # it moved: start again from the reads that say where
        else:
            self.outliers.pop(name, None)
            self.reads.setdefault(name, deque(maxlen=self.window)).append(read)
        self.estimate[name] = self._combine(list(self.reads[name]), order)
        return self.estimate[name]

    def _agrees(self, estimate: FilteredPose, read: FilteredPose, order: int) -> bool:
        if np.linalg.norm(read.pos - estimate.pos) > self.gate:
            return False
        return not order or abs(_turn(read.yaw, estimate.yaw, order)) <= self.gate_rad

    @staticmethod
    def _combine(reads: list[FilteredPose], order: int) -> FilteredPose:
        pos = np.median(np.stack([r.pos for r in reads]), axis=0)
        yaw = reads[-1].yaw
        if order:
            offsets = [_turn(r.yaw, yaw, order) for r in reads]  # each read's yaw nearest the last one's
            yaw = float(yaw + np.arctan2(np.mean(np.sin(offsets)), np.mean(np.cos(offsets))))
        halves = [r.half for r in reads if r.half is not None]
        return FilteredPose(pos, yaw, float(np.median(halves)) if halves else None)


def _turn(yaw: float, reference: float, order: int) -> float:
    """``yaw - reference`` reduced by the multiples of ``2 pi / order`` to ``[-pi / order, pi / order)``."""
    period = 2 * np.pi / order
    return float((yaw - reference + period / 2) % period - period / 2)
