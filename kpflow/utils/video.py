"""Videos from RGB frames: mp4 (libx264 via imageio-ffmpeg) or gif, written atomically and checked complete."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import imageio.v2 as imageio
import numpy as np

from kpflow.utils.io import atomic_path

GIF_TRAILER = b"\x3b"  # the byte that ends every complete GIF


def write_video(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: int = 10) -> Path:
    """Write RGB frames as an mp4 (libx264 via imageio-ffmpeg) or a gif, chosen by the suffix.

    The video is written to a temporary beside ``path`` and read back before it is renamed to ``path``: an mp4 must
    decode to every frame, a gif must decode and end with its trailer. ffmpeg runs as a separate process and does
    not tell its writer when a write fails (a full disk), so without the check a truncated, unplayable file would
    be renamed into place. A failed write or an incomplete video raises ``OSError`` naming ``path``, and nothing is
    left at ``path`` (an older file there stays as it was) nor beside it.
    """
    path = Path(path)
    if path.suffix not in (".mp4", ".gif"):
        raise ValueError(f"video path must end in .mp4 or .gif, got {path}")
    if len(frames) == 0:
        raise ValueError("no frames to write")
    with atomic_path(path) as tmp:
        try:
            if path.suffix == ".gif":
                imageio.mimsave(tmp, list(frames), format="GIF", duration=1000 / fps, loop=0)
            else:
                imageio.mimsave(tmp, list(frames), format="FFMPEG", fps=fps, codec="libx264", macro_block_size=1)
        except OSError as e:  # a failed write seen by the writer itself (the gif's; ffmpeg's broken pipe)
            raise OSError(f"{path} was not written: {str(e).strip().splitlines()[0]}") from e
        problem = _incomplete(tmp, len(frames))
        if problem:
            raise OSError(f"{path} was not written: {problem} (is the disk full?)")
    return path


def _incomplete(video: Path, n_frames: int) -> str | None:
    """Why the video file ``video`` of ``n_frames`` frames is not complete, or None when it is."""
    if video.suffix == ".gif":
        try:
            imageio.mimread(video, format="GIF", memtest=False)
        except Exception as e:  # noqa: BLE001 -- whatever the reader trips on, the file is not a whole gif
            return f"the gif written does not decode ({type(e).__name__}: {e})"
        with open(video, "rb") as f:
            f.seek(-1, os.SEEK_END)
            if f.read(1) != GIF_TRAILER:
                return "the gif written has no trailer (it was cut short)"
        return None
    import imageio_ffmpeg

    try:
        readable = imageio_ffmpeg.count_frames_and_secs(str(video))[0]
    except RuntimeError as e:
        reason = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        return f"ffmpeg cannot read the mp4 written back ({reason})"
    if readable != n_frames:
        return f"the mp4 written holds {readable} of its {n_frames} frames"
    return None
