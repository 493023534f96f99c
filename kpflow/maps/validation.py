"""Input checks shared by every transportation map: each failure names the problem."""

from __future__ import annotations

import math
import numbers
from typing import Callable

import torch

#: the floating dtypes the maps compute in; integer (and bool) inputs are converted to float by design
SUPPORTED_DTYPES = (torch.float32, torch.float64)


def as_float_tensor(x, name: str, like: torch.Tensor | None = None) -> torch.Tensor:
    """Convert ``x`` to a floating tensor (on ``like``'s device and dtype when given).

    Integer and bool inputs are converted; half-precision (float16, bfloat16, float8) and complex inputs raise,
    since the maps' linear algebra needs float32 or float64 and a complex input has no real meaning here.
    """
    if not isinstance(x, torch.Tensor):
        x = torch.as_tensor(x)
    if (x.is_complex() or torch.is_floating_point(x)) and x.dtype not in SUPPORTED_DTYPES:
        kind = "complex " if x.is_complex() else ""
        raise ValueError(
            f"{name} has {kind}dtype {x.dtype}, which transport maps do not support: use float32 or float64 "
            "(integer inputs are converted to float)"
        )
    if like is not None:
        if x.device != like.device:
            raise ValueError(f"{name} is on {x.device} but the map was fitted on {like.device}")
        x = x.to(like.dtype)
    elif not torch.is_floating_point(x):
        x = x.to(torch.get_default_dtype())
    return x


def check_positive(name: str, value, *, optional: bool = False, what: str = "") -> None:
    """Raise ``ValueError`` naming ``name`` and ``value`` unless ``value`` is a finite number > 0 (or ``None``
    when ``optional``). ``what`` says what the argument is, for the message."""
    if optional and value is None:
        return
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value) and value > 0
    if not ok:
        also = " or None" if optional else ""
        raise ValueError(f"{name} must be a positive finite number{also}; got {value!r}{what}")


def check_count(name: str, value, minimum: int = 0, what: str = "") -> None:
    """Raise ``ValueError`` naming ``name`` and ``value`` unless ``value`` is an integer >= ``minimum``."""
    if not (isinstance(value, numbers.Integral) and not isinstance(value, bool) and value >= minimum):
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}{what}")


def scale_floor(x: torch.Tensor, rel: float = 1e-12) -> torch.Tensor:
    """Smallest spread worth normalising ``x`` by: ``rel`` times the magnitude of ``x`` (never an absolute floor,
    so keypoints at any scale are normalised alike), and at least the dtype's smallest normal number."""
    return (rel * x.detach().abs().amax()).clamp_min(torch.finfo(x.dtype).tiny)


def check_finite(x: torch.Tensor, name: str) -> None:
    if not torch.isfinite(x).all():
        bad = (~torch.isfinite(x)).nonzero()[0].tolist()
        raise ValueError(f"{name} contains NaN or inf (first at index {bad})")


def check_pairs(source, target, min_points: Callable[[int], int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate keypoint pairs ``source [*B, N, D]`` and ``target [*B, N, D]`` (batch dims broadcast).

    Raises ``ValueError`` for: a dtype other than float32/float64 (integers are converted), fewer than two
    dimensions, mismatched N or D, fewer than ``min_points`` keypoints (``min_points(D)``), NaN/inf, and two coinciding source keypoints whose targets differ (no map can send one point
    to two places). Returns float tensors of a common dtype, broadcast to a common batch shape.
    """
    source = as_float_tensor(source, "source")
    target = as_float_tensor(target, "target")
    for name, t in (("source", source), ("target", target)):
        if t.ndim < 2:
            raise ValueError(f"{name} must have shape [..., N, D]; got {tuple(t.shape)}")
    if source.shape[-2:] != target.shape[-2:]:
        raise ValueError(
            f"source has shape [N={source.shape[-2]}, D={source.shape[-1]}] per set but target has "
            f"[N={target.shape[-2]}, D={target.shape[-1]}]: keypoints must correspond one to one"
        )
    if source.device != target.device:
        raise ValueError(f"source is on {source.device} but target is on {target.device}")
    n, need = source.shape[-2], min_points(source.shape[-1])
    if n < need:
        raise ValueError(f"too few keypoints: this map needs at least {need} in {source.shape[-1]}-D, got {n}")
    check_finite(source, "source")
    check_finite(target, "target")
    dtype = torch.promote_types(source.dtype, target.dtype)
    batch = source.shape[:-2]
    if target.shape[:-2] != batch:  # (the common case of equal shapes skips the broadcast: fits can be sub-ms)
        try:
            batch = torch.broadcast_shapes(source.shape[:-2], target.shape[:-2])
        except RuntimeError as e:
            raise ValueError(
                f"source batch shape {tuple(source.shape[:-2])} and target batch shape "
                f"{tuple(target.shape[:-2])} do not broadcast"
            ) from e
        source = source.expand(*batch, *source.shape[-2:])
        target = target.expand(*batch, *target.shape[-2:])
    source, target = source.to(dtype), target.to(dtype)
    _check_duplicates(source, target)
    return source, target


def _check_duplicates(source: torch.Tensor, target: torch.Tensor) -> None:
    n, d = source.shape[-2:]
    source, target = source.reshape(-1, n, d), target.reshape(-1, n, d)
    # relative to the set's own extent (no absolute floor, so keypoints at any scale are judged alike)
    scale = (source.amax(-2) - source.amin(-2)).norm(dim=-1).clamp_min(torch.finfo(source.dtype).tiny)  # [B]
    tol = (1e-9 if source.dtype == torch.float64 else 1e-6) * scale
    # direct differences: the matrix-product form cdist uses for N > 25 leaves errors of sqrt(eps) |x| (far above
    # tol for keypoints away from the origin), so exact duplicates could pass unnoticed
    with torch.no_grad():  # a check, never differentiated
        dist = torch.cdist(source, source, compute_mode="donot_use_mm_for_euclid_dist")
        dist.diagonal(dim1=-2, dim2=-1).fill_(torch.inf)  # a keypoint is not its own duplicate
    close = dist <= tol[:, None, None]  # [B, N, N]
    if not close.any():
        return
    b, i, j = close.nonzero().T  # only coinciding sources need their targets compared
    clash = (target[b, i] - target[b, j]).norm(dim=-1) > 1e3 * tol[b]
    if clash.any():
        k = clash.nonzero()[0, 0]
        raise ValueError(
            f"duplicate source keypoints {int(i[k])} and {int(j[k])} coincide but their targets differ: "
            "no map can send one point to two places"
        )
