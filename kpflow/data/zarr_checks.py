"""Reading zarr v2 arrays with errors that name the store, the field and what is damaged.

zarr reads a missing chunk as the array's fill value and reports damaged metadata or chunks with errors that name
neither the file nor the field (``JSONDecodeError``, ``RuntimeError: error during blosc decompression``). These
helpers turn every such case into a ``ValueError`` that says where and what.
"""

from __future__ import annotations

import itertools
import json
import math
from typing import Any

import numpy as np
import zarr


def open_array(group: zarr.Group, name: str, where: str) -> zarr.Array:
    """``group[name]`` as an array; damaged or foreign ``.zarray`` metadata raises naming the field."""
    try:
        array = group[name]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{where}: field {name!r} has damaged metadata ({group.path + '/' if group.path else ''}{name}/.zarray: {type(e).__name__}: {e})") from e
    if not isinstance(array, zarr.Array):
        raise ValueError(f"{where}: {name!r} is a group, not an array")
    return array


def missing_chunks(array: zarr.Array, rows: int) -> list[str]:
    """Keys of the chunks that hold rows ``[0, rows)`` of ``array`` but are not in its store.

    zarr writes every chunk it is given (``write_empty_chunks``), so a missing one was lost, not skipped, and reading
    it would silently return the fill value.
    """
    if rows <= 0:
        return []
    sep = getattr(array, "_dimension_separator", None) or "."
    grid = [range(math.ceil(rows / array.chunks[0]))]
    grid += [range(math.ceil(n / c)) for n, c in zip(array.shape[1:], array.chunks[1:])]
    prefix = f"{array.path}/" if array.path else ""
    keys = (prefix + sep.join(map(str, idx)) for idx in itertools.product(*grid))
    return [k for k in keys if k not in array.chunk_store]


def check_chunks(array: zarr.Array, rows: int, where: str, field: str) -> None:
    """Raise ``ValueError`` naming the field if a chunk holding rows ``[0, rows)`` is missing."""
    lost = missing_chunks(array, rows)
    if lost:
        raise ValueError(
            f"{where}: field {field!r} is missing {len(lost)} chunk(s) of its first {rows} rows ({', '.join(lost[:3])}"
            f"{', ...' if len(lost) > 3 else ''}): those rows were lost and would read as {array.fill_value!r}"
        )


def read(array: zarr.Array, selection: Any, where: str, field: str) -> np.ndarray:
    """``array[selection]``; a chunk that does not decode raises naming the field."""
    try:
        return array[selection]
    except (RuntimeError, ValueError, TypeError, OSError) as e:
        raise ValueError(f"{where}: field {field!r} could not be read: a chunk is damaged ({type(e).__name__}: {e})") from e
