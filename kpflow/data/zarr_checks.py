"""Reading zarr v2 stores so that a store can neither run code nor allocate without bound, with errors that name the
store, the field and what is wrong.

A zarr array's ``.zarray`` names the codecs that decode its chunks, and numcodecs' ``pickle`` filter (or an object
dtype) unpickles a chunk's bytes: reading such an array runs whatever the file says. A chunk's compressed header,
and an array's chunk shape, say how much memory decoding takes. So every kpflow zarr read goes through
:class:`CheckedStore`, a ``DirectoryStore`` that checks what it hands to zarr, before zarr builds a codec or decodes
a byte:

- every ``.zarray`` (:func:`check_array_metadata`): zarr format 2; a plain numeric dtype (:data:`DTYPE_KINDS`: bool,
  signed and unsigned integers, floats, at most 8 bytes; no object, string, structured or sub-array dtype); a
  compressor among :data:`COMPRESSORS` (blosc, or none); no filters; a chunk of at most :data:`MAX_CHUNK_BYTES`;
- every chunk: its size on disk, before it is read, is at most one chunk plus blosc's overhead (a sparse file can
  declare gigabytes it does not hold), and its decoded size, read from the blosc header (or its length,
  uncompressed), is exactly one chunk; ``.zattrs`` is at most :data:`MAX_ATTRS_BYTES` on disk.

Anything else raises :class:`UnsafeStoreError` naming the store, the array and the offending entry. Beyond that,
zarr reads a missing chunk as the array's fill value and reports damaged metadata or chunks with errors that name
neither the file nor the field; :func:`open_array`, :func:`check_chunks` and :func:`read` turn those into
``ValueError`` s that say where and what.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import struct
from typing import Any

import numpy as np
import zarr

#: numpy dtype kinds a stored array may have: bool, signed and unsigned integers, floats.
DTYPE_KINDS = "biuf"
#: compressors a stored array may name (``None``: uncompressed); each one's decoded size is checked before decoding.
COMPRESSORS = ("blosc",)
#: the largest decoded chunk read (256 MiB; Diffusion Policy's image chunks are 18 MB, kpflow writes at most 4 MB).
MAX_CHUNK_BYTES = 256 << 20
#: the largest .zattrs read (a store's checksums and episode records: a few MB for 10^5 episodes).
MAX_ATTRS_BYTES = 64 << 20
_BLOSC_OVERHEAD = 16 + 256  # blosc 1's largest overhead over the raw bytes (16), with room to spare
#: the largest ``.zarray`` read (its JSON is tiny; anything bigger is not zarr metadata).
MAX_METADATA_BYTES = 64 << 10
_MAX_DIMS = 8
_BLOSC_HEADER = struct.Struct("<BBBBIII")


class UnsafeStoreError(ValueError):
    """A zarr array names a codec or dtype that could run code, or a size that could exhaust memory; nothing of it
    was decoded."""


def check_array_metadata(raw: bytes, where: str) -> dict[str, Any]:
    """The parsed ``.zarray`` ``raw`` of the array at ``where``, if kpflow may decode it (module docstring).

    Returns ``{"dtype", "chunks", "compressor", "chunk_bytes"}``. Raises :class:`UnsafeStoreError` naming the entry
    that is refused, ``ValueError`` for metadata that is not a zarr v2 array's."""
    if len(raw) > MAX_METADATA_BYTES:
        raise UnsafeStoreError(f"{where}/.zarray is {len(raw)} bytes, not zarr metadata; refusing to read it")
    meta = json.loads(raw)  # a JSONDecodeError or UnicodeDecodeError is reported by open_array, naming the field
    if not isinstance(meta, dict) or meta.get("zarr_format") != 2:
        raise ValueError(f"{where}/.zarray is not zarr v2 array metadata")
    dtype = _dtype(meta.get("dtype"), where)
    shape, chunks = meta.get("shape"), meta.get("chunks")
    ints = all(
        isinstance(v, list) and len(v) <= _MAX_DIMS and all(isinstance(n, int) and not isinstance(n, bool) for n in v)
        for v in (shape, chunks)
    )
    if not ints or len(shape) != len(chunks) or min(shape, default=0) < 0 or min(chunks, default=1) < 1:
        raise ValueError(f"{where}/.zarray has an invalid shape {shape!r} or chunks {chunks!r}")
    chunk_bytes = math.prod(chunks) * dtype.itemsize
    if chunk_bytes > MAX_CHUNK_BYTES:
        raise UnsafeStoreError(
            f"{where}: one chunk of {chunks} x {dtype} would take {chunk_bytes / 2**20:.0f} MiB to decode; kpflow reads "
            f"chunks of at most {MAX_CHUNK_BYTES >> 20} MiB"
        )
    compressor, filters = meta.get("compressor"), meta.get("filters")
    codec = None if compressor is None else compressor.get("id") if isinstance(compressor, dict) else compressor
    if compressor is not None and codec not in COMPRESSORS:
        raise UnsafeStoreError(
            f"{where}: compressor {codec!r} is not one kpflow decodes ({', '.join(COMPRESSORS)} or none): re-encode the "
            "array with blosc"
        )
    if filters not in (None, []):
        names = [f.get("id") if isinstance(f, dict) else f for f in filters] if isinstance(filters, list) else filters
        raise UnsafeStoreError(
            f"{where}: filters {names!r} are refused (numcodecs' filters include pickle, which runs code when a chunk is "
            "read); kpflow reads arrays without filters"
        )
    if meta.get("order", "C") not in ("C", "F") or meta.get("dimension_separator", ".") not in (".", "/"):
        raise ValueError(f"{where}/.zarray has an invalid order or dimension_separator")
    return {"dtype": dtype, "chunks": tuple(chunks), "compressor": codec, "chunk_bytes": chunk_bytes}


def _dtype(spec: Any, where: str) -> np.dtype:
    if not isinstance(spec, str):
        raise UnsafeStoreError(
            f"{where}: dtype {spec!r} is structured; kpflow reads plain numeric arrays ({DTYPE_KINDS})"
        )
    try:
        dtype = np.dtype(spec)
    except TypeError:
        raise ValueError(f"{where}/.zarray names an unknown dtype {spec!r}") from None
    if dtype.kind not in DTYPE_KINDS or dtype.fields is not None or dtype.subdtype is not None or dtype.itemsize > 8:
        raise UnsafeStoreError(
            f"{where}: dtype {spec!r} is refused (object and string dtypes decode through pickle-capable codecs); kpflow "
            "reads bool, integer and float arrays"
        )
    return dtype


def check_chunk(raw: bytes, meta: dict[str, Any], where: str, key: str) -> None:
    """Raise :class:`UnsafeStoreError` unless chunk ``raw`` of an array with metadata ``meta`` (from
    :func:`check_array_metadata`) decodes to exactly one chunk: its blosc header says so, or, uncompressed, its
    length."""
    expected = meta["chunk_bytes"]
    if meta["compressor"] is None:
        size = len(raw)
    else:  # the blosc 1 header: version, versionlz, flags, typesize (1 byte each), nbytes, blocksize, cbytes (uint32 LE)
        if len(raw) < _BLOSC_HEADER.size:
            raise ValueError(f"{where}: chunk {key} is damaged: {len(raw)} bytes, shorter than a blosc header")
        *_, size, _, compressed = _BLOSC_HEADER.unpack_from(raw)
        if compressed != len(raw):
            raise ValueError(
                f"{where}: chunk {key} is damaged: its header says {compressed} bytes, the file holds {len(raw)}"
            )
    if size != expected:
        raise UnsafeStoreError(
            f"{where}: chunk {key} decodes to {size} bytes, but a chunk of this array is {expected}: refusing to decode it"
        )


class CheckedStore(zarr.storage.DirectoryStore):
    """A zarr ``DirectoryStore`` that checks each ``.zarray`` and chunk before zarr sees it (module docstring)."""

    def __init__(self, path: str | os.PathLike) -> None:
        super().__init__(str(path))
        self._arrays: dict[str, dict[str, Any]] = {}  # array path -> its checked metadata

    def __getitem__(self, key: str) -> bytes:
        parent, _, name = key.rpartition("/")
        self._check_size(key, name)  # before the file is read: a sparse file can declare gigabytes
        value = super().__getitem__(key)
        if name == ".zarray":
            self._arrays[parent] = check_array_metadata(value, f"{self.path}/{parent}")
        elif name not in (".zattrs", ".zgroup"):
            array = self._array_of(key)
            check_chunk(value, self._meta(array), f"{self.path}/{array}", key)
        return value

    def _check_size(self, key: str, name: str) -> None:
        """Refuse a file larger than what it can hold: ``.zarray``/``.zgroup`` beyond :data:`MAX_METADATA_BYTES`,
        ``.zattrs`` beyond :data:`MAX_ATTRS_BYTES`, a chunk
        beyond its array's chunk plus blosc's 16-byte overhead."""
        try:
            size = os.stat(os.path.join(self.path, key)).st_size
        except OSError:
            return  # missing: zarr's own KeyError follows
        if name == ".zattrs":
            most = MAX_ATTRS_BYTES
        elif name in (".zarray", ".zgroup"):
            most = MAX_METADATA_BYTES
        else:
            most = self._meta(self._array_of(key))["chunk_bytes"] + _BLOSC_OVERHEAD
        if size > most:
            raise UnsafeStoreError(
                f"{self.path}: {key} is {size} bytes on disk, more than it can hold ({most}); refusing to read it"
            )

    def __setitem__(self, key: str, value) -> None:
        super().__setitem__(key, value)
        parent, _, name = key.rpartition("/")
        if name == ".zarray":  # this process's own writes (create, resize) are re-checked when next read
            self._arrays.pop(parent, None)

    def _array_of(self, key: str) -> str:
        """The array path of chunk ``key`` (the longest known array path it lies under, else its folder)."""
        known = [a for a in self._arrays if key.startswith(a + "/")]
        return max(known, key=len) if known else key.rpartition("/")[0]

    def _meta(self, array: str) -> dict[str, Any]:
        if array not in self._arrays:
            self[f"{array}/.zarray" if array else ".zarray"]
        return self._arrays[array]


def open_group(path: str | os.PathLike, mode: str, what: str = "zarr store") -> zarr.Group:
    """``zarr.open_group`` on a :class:`CheckedStore` at ``path``; a damaged ``.zgroup``/``.zattrs`` raises
    ``ValueError``: ``<path> is not a readable <what>: ...``."""
    try:
        return zarr.open_group(store=CheckedStore(path), mode=mode)
    except UnsafeStoreError:
        raise
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, ValueError) as e:
        raise ValueError(f"{path} is not a readable {what}: damaged .zgroup/.zattrs ({type(e).__name__}: {e})") from e


def open_array(group: zarr.Group, name: str, where: str) -> zarr.Array:
    """``group[name]`` as an array; damaged, foreign or refused ``.zarray`` metadata raises naming the field."""
    try:
        array = group[name]
    except UnsafeStoreError:
        raise
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as e:
        raise ValueError(
            f"{where}: field {name!r} has damaged metadata ({group.path + '/' if group.path else ''}{name}/.zarray: {type(e).__name__}: {e})"
        ) from e
    if not isinstance(array, zarr.Array):
        raise ValueError(f"{where}: {name!r} is a group, not an array")
    return array


def missing_chunks(array: zarr.Array, rows: int, limit: int | None = None) -> list[str]:
    """Keys of the chunks that hold rows ``[0, rows)`` of ``array`` but are not in its store (the first ``limit``).

    zarr writes every chunk it is given (``write_empty_chunks``), so a missing one was lost, not skipped, and reading
    it would silently return the fill value. The keys are looked up lazily, so with a ``limit`` metadata that claims
    billions of chunks costs at most as many lookups as there are chunk files, plus ``limit``.
    """
    if rows <= 0:
        return []
    sep = getattr(array, "_dimension_separator", None) or "."
    counts = [math.ceil(rows / array.chunks[0])] + [math.ceil(n / c) for n, c in zip(array.shape[1:], array.chunks[1:])]
    prefix = f"{array.path}/" if array.path else ""
    keys = (prefix + sep.join(map(str, idx)) for idx in _grid(counts))
    return list(itertools.islice((k for k in keys if k not in array.chunk_store), limit))


def _grid(counts: list[int]):
    """Every chunk index of a grid with ``counts`` chunks per axis, in C order, one at a time (``itertools.product``
    would first build each axis' range as a tuple)."""
    if min(counts, default=1) < 1:
        return
    index = [0] * len(counts)
    while True:
        yield tuple(index)
        for axis in reversed(range(len(counts))):
            index[axis] += 1
            if index[axis] < counts[axis]:
                break
            index[axis] = 0
        else:
            return


def check_chunks(array: zarr.Array, rows: int, where: str, field: str) -> None:
    """Raise ``ValueError`` naming the field if a chunk holding rows ``[0, rows)`` is missing."""
    lost = missing_chunks(array, rows, limit=4)
    if lost:
        raise ValueError(
            f"{where}: field {field!r} is missing chunk(s) of its first {rows} rows ({', '.join(lost[:3])}"
            f"{', ...' if len(lost) > 3 else ''}): those rows were lost and would read as {array.fill_value!r}"
        )


def read(array: zarr.Array, selection: Any, where: str, field: str) -> np.ndarray:
    """``array[selection]``; a chunk that does not decode raises naming the field (a refused one as
    :class:`UnsafeStoreError`)."""
    try:
        return array[selection]
    except UnsafeStoreError:
        raise
    except (RuntimeError, ValueError, TypeError, OSError) as e:
        raise ValueError(
            f"{where}: field {field!r} could not be read: a chunk is damaged ({type(e).__name__}: {e})"
        ) from e
