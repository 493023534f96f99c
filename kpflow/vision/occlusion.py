"""Reads of a partly hidden object refused by its footprint, so that a hand over an object does not move it.

A camera sees only the part of an object nothing stands in front of. As the jaws come down over a square nut's
handle they hide it, and the rectangle fitted to what is left (:func:`~kpflow.vision.boxes.fit_footprint_box`) is
the ring alone: square, so its longer axis and the end the ring is at are a guess, and the nut's keypoints land
15-20 cm off, turned half round (results/camera_keypoints.md). An object at rest keeps its size, so
:class:`FootprintGate` remembers each object's footprint from its first read in a scene (its half sides along the
rectangle's longer and shorter axes) and refuses a later read whose half sides differ from those by more than
``tolerance`` (m) along either axis: the read names a smaller (or merged, larger) object, and the object keeps the
pose it was last seen at. The footprint is kept for the scene, through grasps and releases (a nut or a cube set
down or dropped lies on the same face); :meth:`FootprintGate.forget` drops it (an object that may lie otherwise now).
"""

from __future__ import annotations

import numpy as np

from .boxes import FootprintBox


class OccludedRead(ValueError):
    """A read whose footprint is not the object's (module docstring): part of it is hidden."""


class FootprintGate:
    """Per-object footprint check over a scene's reads (module docstring); ``tolerance`` in m (> 0)."""

    def __init__(self, tolerance: float = 0.005) -> None:
        if not (np.isfinite(tolerance) and tolerance > 0):
            raise ValueError(f"the footprint tolerance must be a positive number of metres; got {tolerance!r}")
        self.tolerance = float(tolerance)
        self.reset()

    def reset(self) -> None:
        """Forget every footprint (a new scene)."""
        self.footprints: dict[str, np.ndarray] = {}

    def forget(self, name: str) -> None:
        """Forget object ``name``'s footprint (it was moved on purpose)."""
        self.footprints.pop(name, None)

    def check(self, name: str, box: FootprintBox) -> None:
        """Accept ``box`` as a read of object ``name`` (its first one sets the footprint), or raise
        :class:`OccludedRead` naming both footprints."""
        half = np.asarray(box.half, float)
        known = self.footprints.setdefault(name, half.copy())
        off = np.abs(half - known)
        if (off > self.tolerance).any():
            raise OccludedRead(
                f"{name!r} seen with half sides {np.round(1e3 * half, 1).tolist()} mm against its "
                f"{np.round(1e3 * known, 1).tolist()} mm: part of it is hidden (tolerance {1e3 * self.tolerance:.1f} mm)"
            )
