"""The policy server's wire format: msgpack with numpy arrays, and nothing that could run code when read.

An array travels as the map ``{"__ndarray__": True, "data": <raw bytes>, "dtype": <dtype.str>, "shape": [...]}``
and a numpy scalar as ``{"__npgeneric__": True, "data": ..., "dtype": ...}``: the layout openpi's websocket policy
server uses (``openpi_client.msgpack_numpy``), so its clients can talk to kpflow's server. Reading builds arrays with
``np.frombuffer`` for the plain numeric and boolean dtypes only (:data:`DTYPES`); object, string, void and any other
dtype is refused, as is a buffer whose length does not match its shape. msgpack itself builds only maps, lists,
strings, bytes, numbers, booleans and None; there is no pickle anywhere.
"""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np

#: The dtypes an array may have on the wire (little-endian, as ``dtype.str`` spells them, plus their big-endian twins).
DTYPES = frozenset(
    np.dtype(t).newbyteorder(order).str
    for t in (
        "bool",
        "int8",
        "int16",
        "int32",
        "int64",
        "uint8",
        "uint16",
        "uint32",
        "uint64",
        "float16",
        "float32",
        "float64",
    )
    for order in "<>"
)


class WireError(ValueError):
    """Bytes that are not a well-formed message (not msgpack, or an array that cannot be rebuilt safely)."""


def _encode(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        if obj.dtype.str not in DTYPES:
            raise TypeError(f"arrays of dtype {obj.dtype} cannot be sent (allowed: bool, int, uint, float)")
        return {
            "__ndarray__": True,
            "data": np.ascontiguousarray(obj).tobytes(),
            "dtype": obj.dtype.str,
            "shape": list(obj.shape),
        }
    if isinstance(obj, np.generic):
        if obj.dtype.str not in DTYPES:
            raise TypeError(f"scalars of dtype {obj.dtype} cannot be sent")
        return {"__npgeneric__": True, "data": obj.tobytes(), "dtype": obj.dtype.str}
    raise TypeError(f"cannot send an object of type {type(obj).__name__}")


def _decode(obj: dict) -> Any:
    if obj.get("__ndarray__") is True:
        return _array(obj)
    if obj.get("__npgeneric__") is True:
        return _array({**obj, "shape": []})[()]
    return obj


def _array(obj: dict) -> np.ndarray:
    dtype, shape, data = obj.get("dtype"), obj.get("shape"), obj.get("data")
    if dtype not in DTYPES:
        raise WireError(f"array dtype {dtype!r} is not allowed (bool, int, uint or float only)")
    if not (isinstance(shape, list) and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)):
        raise WireError(f"array shape must be a list of non-negative integers, got {shape!r}")
    if not isinstance(data, bytes):
        raise WireError("array data must be bytes")
    dtype = np.dtype(dtype)
    if len(data) != math.prod(shape) * dtype.itemsize:
        raise WireError(
            f"array of shape {shape} and dtype {dtype} needs {math.prod(shape) * dtype.itemsize} bytes, got {len(data)}"
        )
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def pack(obj: Any) -> bytes:
    """``obj`` (maps, lists, strings, numbers, None, numpy arrays and scalars) as msgpack bytes."""
    return msgpack.packb(obj, default=_encode, use_bin_type=True)


def unpack(data: bytes) -> Any:
    """The object in msgpack ``data``, arrays rebuilt as read-only numpy arrays.

    Raises:
        WireError: ``data`` is not one complete msgpack object, or holds an array that cannot be rebuilt safely.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError(
            f"a message must be binary, got {type(data).__name__} (text frames are not part of the protocol)"
        )
    try:
        return msgpack.unpackb(data, object_hook=_decode, raw=False, strict_map_key=True)
    except WireError:
        raise
    except Exception as e:  # msgpack raises several types (ExtraData, FormatError, StackError, ValueError, ...)
        raise WireError(f"not a msgpack message ({type(e).__name__}{': ' if str(e) else ''}{e})") from None
