"""Segmenters: which pixels of a frame belong to which named object.

A :class:`Segmenter` answers ``masks(frame, names) -> [H, W] bool per name``. :class:`InstanceSegmenter` reads the
masks from a frame's instance ids (a renderer's segmentation, or any labelled image), each name standing for a set
of ids; a learned segmenter (an open-vocabulary detector and a promptable mask model) is another implementation of
the same call.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from .cameras import CameraFrame


@runtime_checkable
class Segmenter(Protocol):
    def masks(self, frame: CameraFrame, names: Sequence[str]) -> list[np.ndarray]:
        """One ``[H, W]`` bool mask per name (empty where the object is not seen)."""
        ...


class InstanceSegmenter:
    """Masks from a frame's instance ids: ``ids`` maps each object's name to the ids that make it up."""

    def __init__(self, ids: Mapping[str, Sequence[int]]) -> None:
        self.ids = {name: np.asarray(list(v), np.int64) for name, v in ids.items()}

    def masks(self, frame: CameraFrame, names: Sequence[str]) -> list[np.ndarray]:
        unknown = [n for n in names if n not in self.ids]
        if unknown:
            raise ValueError(f"no instance ids for {unknown}; this segmenter knows {sorted(self.ids)}")
        return [frame.mask_of(self.ids[n]) for n in names]
