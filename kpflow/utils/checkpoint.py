"""Loading Lightning checkpoints with errors that say what is wrong."""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

import lightning

M = TypeVar("M", bound=lightning.LightningModule)


def load_checkpoint(cls: type[M], path: str | Path, map_location: str = "cpu") -> M:
    """``cls.load_from_checkpoint`` on CPU by default (a model trained on a GPU loads anywhere), in eval mode.

    Raises ``FileNotFoundError`` for a missing file and ``ValueError`` naming the file for a corrupt or foreign one.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        model = cls.load_from_checkpoint(path, map_location=map_location)
    except Exception as e:  # torch raises several types for truncated or foreign files
        raise ValueError(f"{path} is not a readable {cls.__name__} checkpoint ({type(e).__name__}: {e})") from e
    return model.eval()
