"""Videos from RGB frames: mp4 (libx264 via imageio-ffmpeg) or gif, written atomically."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import imageio.v2 as imageio
import numpy as np

from kpflow.utils.io import atomic_path


def write_video(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: int = 10) -> Path:
    """Write RGB frames as an mp4 (libx264 via imageio-ffmpeg) or a gif, chosen by the suffix, atomically."""
    path = Path(path)
    if path.suffix not in (".mp4", ".gif"):
        raise ValueError(f"video path must end in .mp4 or .gif, got {path}")
    if len(frames) == 0:
        raise ValueError("no frames to write")
    with atomic_path(path) as tmp:
        if path.suffix == ".gif":
            imageio.mimsave(tmp, list(frames), format="GIF", duration=1000 / fps, loop=0)
        else:
            imageio.mimsave(tmp, list(frames), format="FFMPEG", fps=fps, codec="libx264", macro_block_size=1)
    return path
