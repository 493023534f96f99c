"""Reading Lightning checkpoints without running code from them.

A Lightning checkpoint is a pickle, and unpickling may call any function the file names (``os.system`` through an
object's ``__reduce__``). So every path that reads one, deployment and resumed training alike, goes through
:func:`read_checkpoint`: ``torch.load(weights_only=True)``, whose unpickler builds only tensors and plain
containers (dict, list, tuple, str, numbers, None) and refuses every other global. What a kpflow checkpoint holds
fits that: weights and buffers, plain hyper-parameters, optimiser, scheduler, loop and callback states. A file that
needs more is refused with an error naming it, and so are weights that hold NaN or inf.

- :func:`load_checkpoint` builds a LightningModule from its hyper-parameters and loads its weights (what
  ``load_from_checkpoint`` does, without its ``weights_only=False``); a class with ``migrate_hparams`` (and
  ``complete_state_dict``) first brings an older file's hyper-parameters (and weight names) to its current layout. The hyper-parameters are first checked against
  the weights' shapes on PyTorch's meta device (no memory), so a tiny file whose hyper-parameters ask for a huge
  network is refused before anything is allocated.
- :class:`SafeCheckpointIO` is the Trainer plugin that makes ``trainer.fit(ckpt_path=...)`` read the same way.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path
from typing import Any, Callable, TypeVar

import lightning
import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO

from kpflow.utils.formats import check_zip_expansion
from kpflow.utils.io import atomic_path
from kpflow.utils.limits import check_hyper_parameters
from kpflow.utils.releases import resolve_release

M = TypeVar("M", bound=lightning.LightningModule)


class UnsafeCheckpointError(ValueError):
    """The checkpoint holds pickled objects that only code could rebuild; it was not loaded."""


def read_checkpoint(path: str | Path, map_location: Any = "cpu") -> dict[str, Any]:
    """The checkpoint dict at ``path``, loaded with ``torch.load(weights_only=True)``; ``release:NAME`` names a
    released checkpoint (:func:`kpflow.utils.releases.resolve_release`).

    Raises:
        FileNotFoundError: nothing at ``path`` (for ``release:NAME``: in none of the folders looked in, named).
        UnsafeCheckpointError: the file asks the unpickler for anything but tensors and plain containers (it might
            run code); nothing from it was executed.
        ValueError: the file is not a readable checkpoint (truncated, foreign, no ``state_dict``), or a weight holds
            NaN or inf (the message names the tensor).
    """
    path = resolve_release(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    check_zip_expansion(path)  # a compressed entry could expand to gigabytes inside torch.load
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
        raise ValueError(
            f"{path} is not a readable checkpoint (not a torch file: {unpickling_reason(lines)})"
        ) from None
    except Exception as e:  # torch raises several types for truncated or foreign files
        reason = (
            f"{type(e).__name__}: {e}"
            if str(e)
            else ("the file is empty" if path.stat().st_size == 0 else type(e).__name__)
        )
        raise ValueError(f"{path} is not a readable checkpoint, truncated or not a torch file ({reason})") from None
    if not isinstance(checkpoint, dict) or not isinstance(checkpoint.get("state_dict"), dict):
        raise ValueError(f"{path} is not a Lightning checkpoint: no state_dict")
    check_finite(checkpoint["state_dict"], path)
    return checkpoint


def unpickling_reason(lines: list[str]) -> str:
    """What torch's weights-only unpickler objected to, from its error's ``lines``: the line after its
    ``WeightsUnpickler error:`` header (e.g. ``Unsupported operand 103``), without the advice around it."""
    for i, line in enumerate(lines):
        if "WeightsUnpickler error:" in line:
            rest = [line.split("WeightsUnpickler error:", 1)[1].strip(), *lines[i + 1 :]]
            return next((part for part in rest if part), "unreadable")
    return next((line for line in lines if line), "unreadable")


def shape_mismatches(expected: dict[str, Any], held: dict[str, Any]) -> list[str]:
    """How the tensors ``held`` (a file's state_dict) differ from the ``expected`` ones (a module's, e.g. built on the
    meta device): names missing from the file, shapes that differ, names the module does not have; in that order."""
    shape = {name: list(t.shape) for name, t in held.items() if isinstance(t, torch.Tensor)}
    problems = [f"{name!r} missing from the file" for name in expected if name not in shape]
    problems += [f"{name!r} is {shape[name]} in the file, {list(t.shape)} by the hyper-parameters"
                 for name, t in expected.items() if name in shape and shape[name] != list(t.shape)]  # fmt: skip
    return problems + [f"{name!r} in the file is not in the model" for name in held if name not in expected]


def check_finite(state_dict: dict[str, Any], path: str | Path) -> None:
    """Raise ``ValueError`` naming ``path`` and the first floating tensor of ``state_dict`` with NaN or inf."""
    for name, value in state_dict.items():
        if isinstance(value, torch.Tensor) and value.is_floating_point() and not torch.isfinite(value).all():
            bad = int((~torch.isfinite(value)).sum())
            raise ValueError(
                f"{path}: weight {name!r} holds {bad} NaN or inf value(s) of {value.numel()}; refusing to load it"
            )


def load_checkpoint(cls: type[M], path: str | Path, map_location: Any = "cpu") -> M:
    """A ``cls`` built from the checkpoint's hyper-parameters with its weights loaded, on CPU by default (a model
    trained on a GPU loads anywhere), in eval mode. Reads through :func:`read_checkpoint`.

    Raises ``FileNotFoundError`` for a missing file, :class:`UnsafeCheckpointError` for a file that could run code,
    and ``ValueError`` naming the file for a corrupt or foreign one, non-finite weights, hyper-parameters beyond
    :data:`kpflow.utils.limits.LIMITS` (checked before anything is built), or hyper-parameters that do not build a module with the weights' names and shapes (checked on the meta device before anything is allocated:
    :func:`shape_mismatches`).
    """
    checkpoint = read_checkpoint(path, map_location)
    migrate = getattr(cls, "migrate_hparams", None)  # an older file's hyper-parameters in the class's current layout
    hparams = checkpoint.get("hyper_parameters", {})
    hparams = migrate(hparams) if migrate else hparams
    check_hyper_parameters(hparams, str(path))  # before even the skeleton: its size follows them
    complete = getattr(
        cls, "complete_state_dict", None
    )  # a released file may hold part of the weights (kpflow-release)
    state = complete(checkpoint["state_dict"]) if complete else checkpoint["state_dict"]
    try:
        with torch.device("meta"):  # shapes only, no storage: whatever size the hyper-parameters ask for costs nothing
            skeleton = cls(**hparams)
        problems = shape_mismatches(skeleton.state_dict(), state)
        if not problems:
            model = cls(**hparams)
            model.on_load_checkpoint(checkpoint)
            model.load_state_dict(state)
    except (TypeError, RuntimeError, ValueError) as e:
        raise ValueError(f"{path} is not a readable {cls.__name__} checkpoint ({type(e).__name__}: {e})") from e
    if problems:
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        raise ValueError(
            f"{path}: its hyper-parameters do not match its weights, refusing to build the {cls.__name__}: {'; '.join(problems[:3])}{more}"
        )
    return model.eval()


class SafeCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint IO with reading through :func:`read_checkpoint` (``Trainer(plugins=[SafeCheckpointIO()])``),
    so resuming a run never runs code from its checkpoint, and saving through a temporary file beside the target
    (:func:`~kpflow.utils.io.atomic_path`), so a checkpoint reaches its name only when whole. (Lightning's own save
    writes its temporary into the system's temp folder and moves it; on another filesystem that move is a copy, which
    a full disk can cut short at the final name.) Remote paths (``s3://...``) keep Lightning's save."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any | None = None) -> None:
        if storage_options is not None or "://" in str(path):
            return super().save_checkpoint(checkpoint, path, storage_options)
        buffer = io.BytesIO()  # serialised first, as Lightning does: a failed write is then the file's OSError
        torch.save(checkpoint, buffer)
        with atomic_path(path) as tmp:
            tmp.write_bytes(buffer.getbuffer())

    def load_checkpoint(self, path, map_location: Callable | None = lambda storage, loc: storage) -> dict[str, Any]:
        return read_checkpoint(path, map_location=map_location)
