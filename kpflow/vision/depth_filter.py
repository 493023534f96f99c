"""Filtering of depth, as RGB-D cameras' software does before its points are used: spatially within an object
(RealSense's spatial filter, guided here by the object's mask) and over time (its temporal filter).

:func:`smooth_depth` replaces the depth of each pixel of ``mask`` that has a return by the mean depth of the pixels
of the mask with returns in its ``size x size`` window: within one object the RMS of independent per-pixel noise
falls by up to ``size``, and nothing behind the object (outside its mask) is averaged in. Holes stay holes; pixels
outside the mask keep their depth.

:func:`temporal_mean` averages the depth of ``N`` frames of a still scene pixel by pixel, over the frames with a
return (a hole in all of them stays one): independent per-frame noise falls by ``sqrt(N)``.
"""

from __future__ import annotations

import numpy as np


def smooth_depth(depth: np.ndarray, mask: np.ndarray, size: int = 5) -> np.ndarray:
    """The filtered copy of ``depth [H, W]`` (m; ``<= 0`` or NaN: hole) within ``mask [H, W]`` (module docstring)."""
    if int(size) != size or size < 1 or size % 2 == 0:
        raise ValueError(f"size must be an odd integer >= 1; got {size}")
    d = np.array(depth, np.float64)
    if np.shape(mask) != d.shape:
        raise ValueError(f"mask must be [H, W] = {list(d.shape)} like the depth; got {list(np.shape(mask))}")
    valid = np.isfinite(d) & (d > 0)
    inside = valid & np.asarray(mask, bool)
    out = np.where(valid, d, 0.0)
    if size == 1 or not inside.any():
        return out
    r = int(size) // 2
    padded = np.pad(np.where(inside, d, np.nan), r, constant_values=np.nan)
    v, u = np.nonzero(inside)
    offsets = np.arange(-r, r + 1)
    windows = padded[(v + r)[:, None, None] + offsets[None, :, None], (u + r)[:, None, None] + offsets[None, None, :]]
    out[v, u] = np.nanmean(windows.reshape(len(v), -1), axis=-1)  # the pixel itself is always there
    return out


def temporal_mean(depths) -> np.ndarray:
    """The per-pixel mean ``[H, W]`` of the returns in ``depths [N, H, W]`` (m; ``<= 0`` or NaN: hole; module
    docstring)."""
    d = np.array(depths, np.float64)
    if d.ndim != 3 or not len(d):
        raise ValueError(f"depths must be [N, H, W] with N >= 1; got shape {d.shape}")
    valid = np.isfinite(d) & (d > 0)
    count = valid.sum(0)
    return np.where(count > 0, np.where(valid, d, 0.0).sum(0) / np.maximum(count, 1), 0.0)
