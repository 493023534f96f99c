"""Reading Lightning checkpoints without running code from them.

A Lightning checkpoint is a pickle, and unpickling may call any function the file names (``os.system`` through an
object's ``__reduce__``). So every path that reads one, deployment and resumed training alike, goes through
:func:`read_checkpoint`: ``torch.load(weights_only=True)``, whose unpickler builds only tensors and plain
containers (dict, list, tuple, str, numbers, None) and refuses every other global. What a kpflow checkpoint holds
fits that: weights and buffers, plain hyper-parameters, optimiser, scheduler, loop and callback states. A file that
needs more is refused with an error naming it, and so are weights that hold NaN or inf.

- :func:`load_checkpoint` builds a LightningModule from its hyper-parameters and loads its weights (what
  ``load_from_checkpoint`` does, without its ``weights_only=False``).
- :class:`SafeCheckpointIO` is the Trainer plugin that makes ``trainer.fit(ckpt_path=...)`` read the same way.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any, Callable, TypeVar

import lightning
import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO

M = TypeVar("M", bound=lightning.LightningModule)


class UnsafeCheckpointError(ValueError):
    """The checkpoint holds pickled objects that only code could rebuild; it was not loaded."""


def read_checkpoint(path: str | Path, map_location: Any = "cpu") -> dict[str, Any]:
    """The checkpoint dict at ``path``, loaded with ``torch.load(weights_only=True)``.

    Raises:
        FileNotFoundError: nothing at ``path``.
        UnsafeCheckpointError: the file asks the unpickler for anything but tensors and plain containers (it might
            run code); nothing from it was executed.
        ValueError: the file is not a readable checkpoint (truncated, foreign, no ``state_dict``), or a weight holds
            NaN or inf (the message names the tensor).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        checkpoint = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        lines = [line.strip() for line in str(e).splitlines()]
        globals_ = [line for line in lines if "GLOBAL" in line]  # what the file asked the unpickler to import
        if globals_:
            reason = globals_[0].removeprefix("WeightsUnpickler error: ")
            raise UnsafeCheckpointError(
                f"{path} was refused: it holds pickled objects other than tensors and plain containers, which could "
                f"run code when loaded (kpflow reads checkpoints with torch.load(weights_only=True)): {reason}"
            ) from None
        raise ValueError(f"{path} is not a readable checkpoint ({type(e).__name__}: {lines[-1] if lines else e})") from None
    except Exception as e:  # torch raises several types for truncated or foreign files
        raise ValueError(f"{path} is not a readable checkpoint ({type(e).__name__}: {e})") from e
    if not isinstance(checkpoint, dict) or not isinstance(checkpoint.get("state_dict"), dict):
        raise ValueError(f"{path} is not a Lightning checkpoint: no state_dict")
    check_finite(checkpoint["state_dict"], path)
    return checkpoint


def check_finite(state_dict: dict[str, Any], path: str | Path) -> None:
    """Raise ``ValueError`` naming ``path`` and the first floating tensor of ``state_dict`` with NaN or inf."""
    for name, value in state_dict.items():
        if isinstance(value, torch.Tensor) and value.is_floating_point() and not torch.isfinite(value).all():
            bad = int((~torch.isfinite(value)).sum())
            raise ValueError(f"{path}: weight {name!r} holds {bad} NaN or inf value(s) of {value.numel()}; refusing to load it")


def load_checkpoint(cls: type[M], path: str | Path, map_location: Any = "cpu") -> M:
    """A ``cls`` built from the checkpoint's hyper-parameters with its weights loaded, on CPU by default (a model
    trained on a GPU loads anywhere), in eval mode. Reads through :func:`read_checkpoint`.

    Raises ``FileNotFoundError`` for a missing file, :class:`UnsafeCheckpointError` for a file that could run code,
    and ``ValueError`` naming the file for a corrupt or foreign one or non-finite weights.
    """
    checkpoint = read_checkpoint(path, map_location)
    hparams = checkpoint.get("hyper_parameters", {})
    try:
        model = cls(**hparams)
        model.on_load_checkpoint(checkpoint)
        model.load_state_dict(checkpoint["state_dict"])
    except (TypeError, RuntimeError, ValueError) as e:
        raise ValueError(f"{path} is not a readable {cls.__name__} checkpoint ({type(e).__name__}: {e})") from e
    return model.eval()


class SafeCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint IO with reading through :func:`read_checkpoint` (``Trainer(plugins=[SafeCheckpointIO()])``),
    so resuming a run never runs code from its checkpoint. Saving stays Lightning's, which is already atomic (an
    fsspec transaction: a temporary file moved into place)."""

    def load_checkpoint(self, path, map_location: Callable | None = lambda storage, loc: storage) -> dict[str, Any]:
        return read_checkpoint(path, map_location=map_location)
