"""Episodes on disk in the Diffusion Policy "replay buffer" zarr v2 layout.

A store is a zarr group holding

* ``data/<field>``: one array per field, the episodes concatenated along axis 0 (time);
* ``meta/episode_ends``: int64 ``[E]``, the cumulative exclusive end row of each episode.

so existing datasets such as Diffusion Policy's ``pusht_cchi_v7_replay.zarr`` open as they are.

Crash safety. zarr 2.18's ``DirectoryStore`` writes every key (a chunk, ``.zarray`` or ``.zattrs``) to a
``*.partial`` temporary and renames it into place, so no single key is ever half-written. :meth:`EpisodeStore.add_episode`
writes in three steps:

1. ``meta/.zattrs`` gains ``pending_episode = {"episode": E, "start": s, "end": e}`` (and the episode's attrs);
2. the data rows ``[s, e)``;
3. ``e`` is appended to ``meta/episode_ends``: the commit point. Then the pending mark is cleared.

So the only states a crash can leave are the ones the pending mark describes: data rows past ``s`` (at most up to
``e``), and ``episode_ends`` grown by one entry that reads as its fill value 0 (zarr's append writes the grown
``.zarray`` before the chunk). Readers ignore such an uncommitted episode; mode ``"a"`` removes it before
appending. Everything else that is inconsistent (ends not increasing, an index shorter or longer than the data, data
with an empty index, per-episode attrs beyond the episodes, a missing chunk) is damage, not a torn append: every open
refuses it with an error that says what is wrong, and changes nothing. (This protects against a crashing process,
not against power loss: nothing is fsync'ed.)

Integrity. The first episode records each field's dtype and trailing shape (``meta/.zattrs["fields"]``), and every
episode records an xxh3_64 checksum of each field's rows as written (``meta/.zattrs["checksums"]``: per field, the
episodes' 16-hex-digit checksums concatenated, written with the pending mark so that a committed episode always has
one; one string per field keeps the metadata small to parse). Opening a store
checks its arrays' dtypes and shapes against the record; every read (:meth:`EpisodeStore.episode`,
:meth:`EpisodeStore.field`) checks the rows it returns against their episodes' checksums, and :meth:`EpisodeStore.verify`
(``kpflow-verify STORE``) checks everything. A mismatch raises a ``ValueError`` naming the field and the
episode: edited dtypes, flipped bytes and chunks swapped between fields are refused instead of read as plausible
numbers. Stores written before checksums existed (and foreign ones, such as Diffusion Policy's replay buffers) have
no record: they are read unverified (:attr:`EpisodeStore.sealed` is False; opening one to read says so once per
process, :class:`UnverifiedStoreWarning`, so training and evaluation on it say it too), and appending to one that
holds episodes is refused until ``kpflow-verify seal=true store=STORE`` has recorded their checksums. A store whose
field record survives but whose checksums are gone was sealed: it is refused, saying how to seal it again. Every zarr read goes through
:class:`~kpflow.data.zarr_checks.CheckedStore`: no store can name a codec that runs code or a chunk that exhausts
memory.

One writer at a time: mode ``"a"`` takes an exclusive lock (:class:`~kpflow.utils.file_lock.FileLock`, an
``fcntl.flock`` on ``<store>/.kpflow-write.lock``, released when the store is closed or its process dies) before it looks at the
store. A second writer waits up to ``wait`` seconds (``None``: as long as it takes) and then fails with an error
that says another process is writing. Readers take no lock and see only committed episodes.
"""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np
import xxhash
import zarr
from numcodecs import Blosc

from ..utils.file_lock import FileLock
from .zarr_checks import DTYPE_KINDS, check_chunks, open_array, open_group, read

# Same codec as the standard Push-T replay buffer.
_COMPRESSOR = Blosc(cname="zstd", clevel=5, shuffle=Blosc.BITSHUFFLE)
_MAX_CHUNK_ROWS = 1024
_TARGET_CHUNK_BYTES = 1 << 22  # keep image chunks at a few MB
_EPISODE_ATTRS = "episode_attrs"  # key of the per-episode attrs list in meta/.zattrs
_PENDING = "pending_episode"  # key of the write-ahead mark of an append in progress, in meta/.zattrs
_FIELDS = "fields"  # key of each field's recorded {"dtype", "shape"} (trailing), in meta/.zattrs
_CHECKSUMS = "checksums"  # key of {field: the episodes' xxh3_64 hex digests concatenated}, in meta/.zattrs
_HEX = 16  # hex digits of one checksum
_DIGEST = 8  # its bytes
LOCK_NAME = ".kpflow-write.lock"


def _chunk_rows(row_bytes: int) -> int:
    """Rows per chunk along time: up to 1024, fewer for large rows (images)."""
    return max(1, min(_MAX_CHUNK_ROWS, _TARGET_CHUNK_BYTES // max(row_bytes, 1)))


def episode_digests(values: np.ndarray, ends: list[int]) -> bytes:
    """The xxh3_64 digests (8 bytes each) of consecutive episodes' rows of ``values`` (their bytes in C order, as
    stored), the episodes ending at rows ``ends`` of ``values``: one byte view, one library call per episode."""
    row = values[0].nbytes if len(values) else 0
    data, digest = memoryview(np.ascontiguousarray(values)).cast("B"), xxhash.xxh3_64_digest
    bounds = [end * row for end in ends]
    return b"".join([digest(data[a:b]) for a, b in zip([0, *bounds[:-1]], bounds)])


def _schema(values: Mapping[str, np.ndarray]) -> dict[str, dict[str, Any]]:
    """Each field's dtype (numpy's string, e.g. ``<f4``) and trailing shape, as recorded in ``meta/.zattrs``."""
    return {name: {"dtype": v.dtype.str, "shape": list(v.shape[1:])} for name, v in values.items()}


class UnverifiedStoreWarning(UserWarning):
    """A store without checksums is being read: its values cannot be checked against what was written."""


_WARNED: set[str] = set()


def _warn_unverified(path: Path) -> None:
    """Say once per process and store that ``path`` is read unverified (training and evaluation then say so)."""
    key = str(path.resolve())
    if key not in _WARNED:
        _WARNED.add(key)
        warnings.warn(
            f"{path} has no checksums (written before kpflow recorded them, or by another tool): its values are read "
            f"unverified. kpflow-verify seal=true store={path} reads it whole once and records them",
            UnverifiedStoreWarning,
            stacklevel=3,
        )


def _field_spec_ok(spec: Any) -> bool:
    """Whether a field record's entry is ``{"dtype": str, "shape": [int, ...]}``."""
    return (isinstance(spec, dict) and isinstance(spec.get("dtype"), str) and isinstance(spec.get("shape", []), list)
            and all(isinstance(d, int) and d >= 0 for d in spec.get("shape", [])))  # fmt: skip


def _digests(checksums: Any, where: str) -> dict[str, bytes] | None:
    """``meta/.zattrs["checksums"]`` (None when absent) as bytes per field, 8 per episode; ``ValueError`` when its
    fields disagree in length or it is not hex digests."""
    if checksums is None:
        return None
    try:
        digests = {name: bytes.fromhex(v) for name, v in checksums.items()}
    except (AttributeError, TypeError, ValueError):
        digests = None  # not a dict of strings, or not hex
    lengths = {len(d) for d in digests.values()} if digests else set()
    if (
        digests is None
        or len(lengths) > 1
        or any(len(d) * 2 != len(checksums[n]) or len(d) % _DIGEST for n, d in digests.items())
    ):
        raise ValueError(
            f"{where}: meta/.zattrs' checksums are damaged (each field must hold {_HEX} hex digits per episode)"
        )
    return digests


def _check_ends(ends: np.ndarray, where: str) -> None:
    """Raise unless ``ends`` is strictly increasing from above 0 (every episode has at least one row)."""
    starts = np.concatenate([[0], ends[:-1]])
    bad = np.flatnonzero(ends <= starts)
    if len(bad):
        i = int(bad[0])
        raise ValueError(
            f"{where}: meta/episode_ends is not strictly increasing from 0 at index {i} "
            f"({int(starts[i])} -> {int(ends[i])}): the index is damaged; nothing was changed"
        )


def _uncommitted(
    raw: np.ndarray, pending: Any, rows: dict[str, int], lists: dict[str, int | None], where: str
) -> tuple[int, bool]:
    """How many entries of ``raw`` (the stored ``episode_ends``) are committed, and whether an uncommitted append
    (or a stale pending mark) is left to clean up; raise ``ValueError`` for any state a torn append cannot leave.

    ``rows``: the row count of every data array; ``lists``: the length of each per-episode list in
    ``meta/.zattrs`` (attrs, checksums; None if absent)."""
    n, extra_attrs = len(raw), 0
    if pending is None:
        limit = committed = int(raw[-1]) if n else 0
    else:
        try:
            e, start, end = int(pending["episode"]), int(pending["start"]), int(pending["end"])
        except (KeyError, TypeError, ValueError):
            raise ValueError(
                f"{where}: meta/.zattrs holds a malformed {_PENDING} mark {pending!r}; nothing was changed"
            ) from None
        if n == e + 1 and raw[-1] == 0:  # torn commit: .zarray grown, value not written
            n = e
        elif not (n == e or (n == e + 1 and raw[-1] == end)):  # neither before the commit nor just after it
            raise ValueError(
                f"{where}: an append of episode {e} was in progress, but meta/episode_ends holds {len(raw)} entries: "
                "the index is damaged; nothing was changed"
            )
        prev = int(raw[e - 1]) if e else 0
        if prev != start:
            raise ValueError(
                f"{where}: the pending episode {e} starts at row {start} but episode {e - 1} ends at {prev}: the index is damaged"
            )
        committed = int(raw[n - 1]) if n else 0
        limit, extra_attrs = (end, 1) if n == e else (committed, 0)  # uncommitted: its rows and attrs may be there
    _check_ends(raw[:n], where)
    for name, count in rows.items():
        if count < committed:
            raise ValueError(
                f"{where}: data/{name} has {count} rows but meta/episode_ends says {committed}: rows were lost"
            )
        if count > limit:
            what = "the index is empty" if not n else f"meta/episode_ends ends at row {committed}"
            raise ValueError(
                f"{where}: data/{name} has {count} rows but {what}, and no append was in progress that could have "
                "left them: the index is damaged; nothing was changed"
            )
    for key, count in lists.items():
        if count is not None and count > n + extra_attrs:
            raise ValueError(
                f"{where}: meta/.zattrs lists {key} for {count} episodes but the store holds {n}: the metadata is damaged"
            )
    dirty = pending is not None or n < len(raw) or any(c > committed for c in rows.values())
    return n, dirty


class EpisodeStore:
    """Episodes of equally-named arrays, stored as zarr ``data/<field>`` + ``meta/episode_ends``.

    Args:
        path: directory of the zarr store.
        mode: ``"r"`` read-only (the store must exist) or ``"a"`` (open for appending; created if missing).
        wait: mode ``"a"``: seconds to wait for another writer's lock (0: fail at once; None: wait as long as it
            takes).

    Use it as a context manager (or call :meth:`close`) to release the write lock as soon as you are done.

    Raises:
        FileNotFoundError: mode ``"r"`` and nothing at ``path``.
        TimeoutError: mode ``"a"`` and another writer held the store for longer than ``wait``.
        ValueError: ``path`` is not an episode store, or the store is damaged (the message says how; nothing is
            changed).
    """

    def __init__(self, path: str | Path, mode: str = "r", wait: float | None = 0.0) -> None:
        if mode not in ("r", "a"):
            raise ValueError(f"mode must be 'r' or 'a'; got {mode!r}")
        self.path, self.mode = Path(path), mode
        self._lock: FileLock | None = None
        if self.path.exists() and not self.path.is_dir():
            raise ValueError(f"{self.path} is not an episode store: it is a file, not a zarr directory")
        if mode == "r" and not self.path.exists():
            raise FileNotFoundError(f"no episode store at {self.path}")
        if mode == "r" or not (self.path / LOCK_NAME).exists():  # a folder no writer has touched: refuse it untouched
            self._check_group()
        if mode == "a":
            self._lock = _acquire(self.path, wait)
        try:
            if mode == "a":  # another writer may have been creating the store: look again, holding the lock
                self._check_group()
            self._open()
        except BaseException:
            self.close()
            raise
        if mode == "r" and not self.sealed and self.n_episodes:
            _warn_unverified(self.path)

    def _check_group(self) -> None:
        """Raise ``ValueError`` unless ``path`` is a zarr group, or (mode ``"a"``) nothing but a lock file or nothing."""
        if (self.path / ".zgroup").is_file():
            return
        if self.mode == "r" or any(p.name != LOCK_NAME for p in (self.path.iterdir() if self.path.exists() else ())):
            raise ValueError(f"{self.path} is not an episode store: not a zarr group (no .zgroup)")

    def _open(self) -> None:
        where = str(self.path)
        self._root = open_group(self.path, self.mode, "episode store")
        if self.mode == "a":
            _remove_partials(self.path)
        if "meta/episode_ends" not in self._root:
            self._init_layout()
        if not isinstance(self._root.get("data"), zarr.Group):
            raise ValueError(f"{where} is not an episode store: missing the data group")
        self._data: zarr.Group = self._root["data"]
        self._meta: zarr.Group = self._root["meta"]
        self._ends_array = open_array(self._meta, "episode_ends", where)
        if self._ends_array.ndim != 1 or self._ends_array.dtype.kind not in "iu":
            raise ValueError(
                f"{where}: meta/episode_ends must be a 1-D integer array; it is {self._ends_array.dtype} {list(self._ends_array.shape)}"
            )
        arrays = {name: open_array(self._data, name, where) for name in self._data.array_keys()}
        check_chunks(self._ends_array, self._ends_array.shape[0], where, "meta/episode_ends")  # before reading it whole
        raw = np.asarray(read(self._ends_array, slice(None), where, "meta/episode_ends"), dtype=np.int64)
        try:
            meta_attrs = self._meta.attrs.asdict()
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise ValueError(f"{where}: meta/.zattrs is damaged ({type(e).__name__}: {e})") from e
        if not isinstance(meta_attrs, dict):
            raise ValueError(
                f"{where}: meta/.zattrs is damaged: it holds a JSON {type(meta_attrs).__name__}, not an object of attributes; restore the store from a copy"
            )
        if not isinstance(meta_attrs.get(_EPISODE_ATTRS, []), list):
            raise ValueError(
                f"{where}: meta/.zattrs is damaged: its {_EPISODE_ATTRS} must be a list (one record per episode)"
            )
        pending = meta_attrs.get(_PENDING)
        self._schema: dict[str, dict] | None = meta_attrs.get(_FIELDS)
        self._digests = _digests(meta_attrs.get(_CHECKSUMS), where)
        rows = {name: a.shape[0] for name, a in arrays.items()}
        lists = {
            "attrs": None if meta_attrs.get(_EPISODE_ATTRS) is None else len(meta_attrs[_EPISODE_ATTRS]),
            "checksums": None if self._digests is None else self._n_checksums,
        }
        n, dirty = _uncommitted(raw, pending, rows, lists, where)
        self._ends = raw[:n]
        self._check_schema(arrays, n, pending is not None)
        for name, a in arrays.items():
            check_chunks(a, self.n_steps, where, name)
        if self.mode == "a" and dirty:
            self._drop_uncommitted(arrays, n < len(raw))

    @property
    def _n_checksums(self) -> int:
        """How many episodes the checksum record covers."""
        return len(next(iter(self._digests.values()), b"")) // _DIGEST if self._digests else 0

    def _check_schema(self, arrays: dict[str, zarr.Array], n: int, pending: bool) -> None:
        """Raise ``ValueError`` unless the arrays have the recorded fields, dtypes and shapes, and every committed
        episode its checksums (stores with a record; see the module docstring)."""
        where = str(self.path)
        if self._schema is None:
            if self._digests is not None:
                raise ValueError(f"{where}: meta/.zattrs holds checksums but no field record: the metadata is damaged")
            return
        if not isinstance(self._schema, dict) or not all(_field_spec_ok(spec) for spec in self._schema.values()):
            raise ValueError(
                f"{where}: meta/.zattrs' field record is damaged: it must map each field to {{dtype, shape}}, got {str(self._schema)[:120]!r}"
            )
        if self._digests is None:
            raise ValueError(
                f"{where}: meta/.zattrs records the fields but lost its checksums: the store was sealed and cannot be verified "
                f"now. If you trust its values, seal it again: kpflow-verify seal=true store={where} (after removing the field "
                "record from meta/.zattrs), or restore the store from a copy"
            )
        if set(self._digests) != set(self._schema):
            raise ValueError(
                f"{where}: meta/.zattrs' field record or checksums are damaged (they must list the same fields)"
            )
        if self._n_checksums < n:
            raise ValueError(
                f"{where}: meta/.zattrs holds checksums for {self._n_checksums} episodes but the store has {n}: the metadata is damaged"
            )
        if (n or arrays) and set(arrays) != set(self._schema) and not (pending and not n):
            raise ValueError(
                f"{where}: the store's fields {sorted(arrays)} are not the recorded ones {sorted(self._schema)}"
            )
        for name, a in arrays.items():
            spec = self._schema.get(name, {})
            if spec and (a.dtype != np.dtype(spec.get("dtype")) or list(a.shape[1:]) != list(spec.get("shape", []))):
                raise ValueError(
                    f"{where}: field {name!r} is {a.dtype} {list(a.shape[1:])} on disk but was written as {spec.get('dtype')} "
                    f"{spec.get('shape')}: its metadata was changed after it was written"
                )

    def _init_layout(self) -> None:
        """Create ``data`` and ``meta/episode_ends`` in an empty group; refuse anything else."""
        has_data = isinstance(self._root.get("data"), zarr.Group) and len(list(self._root["data"].array_keys()))
        if self.mode == "r" or has_data:
            raise ValueError(f"{self.path} is not an episode store: missing meta/episode_ends")
        self._root.require_group("data")
        # episode_ends last: its existence marks a complete (empty) store.
        self._root.require_group("meta").create(
            "episode_ends", shape=(0,), chunks=(_MAX_CHUNK_ROWS,), dtype=np.int64, compressor=_COMPRESSOR, fill_value=0
        )

    def _drop_uncommitted(self, arrays: dict[str, zarr.Array], torn_commit: bool) -> None:
        """Mode "a": remove what a crashed :meth:`add_episode` left past the last commit (see the module docstring)."""
        if torn_commit:
            self._ends_array.resize(len(self._ends))
        if not len(self._ends):  # crash during the first episode: it had fixed the fields, forget them
            for name in arrays:
                del self._data[name]
            self._schema = None
        for array in arrays.values():
            if len(self._ends) and array.shape[0] > self.n_steps:
                array.resize((self.n_steps, *array.shape[1:]))
        attrs = dict(self._meta.attrs.asdict())
        attrs.pop(_PENDING, None)
        if _EPISODE_ATTRS in attrs:
            attrs[_EPISODE_ATTRS] = attrs[_EPISODE_ATTRS][: self.n_episodes]
        if _CHECKSUMS in attrs:
            attrs[_CHECKSUMS] = {name: sums[: _HEX * self.n_episodes] for name, sums in attrs[_CHECKSUMS].items()}
        if not len(self._ends):
            attrs.pop(_FIELDS, None)
            attrs.pop(_CHECKSUMS, None)
        self._digests = _digests(attrs.get(_CHECKSUMS), str(self.path))
        self._meta.attrs.put(attrs)

    def close(self) -> None:
        """Release the write lock (mode ``"a"``); the store can no longer be appended to through this object."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def __enter__(self) -> "EpisodeStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_lock", None) is not None:
            self.close()

    # ----------------------------------------------------------------------------------------- reading

    @property
    def n_episodes(self) -> int:
        """Number of committed episodes."""
        return len(self._ends)

    @property
    def n_steps(self) -> int:
        """Total number of committed time steps (rows)."""
        return int(self._ends[-1]) if len(self._ends) else 0

    @property
    def episode_ends(self) -> np.ndarray:
        """Cumulative exclusive end row of each committed episode (int64 copy)."""
        return self._ends.copy()

    @property
    def fields(self) -> tuple[str, ...]:
        """Names of the data arrays (empty until the first episode is committed)."""
        return tuple(sorted(self._data.array_keys())) if self.n_episodes else ()

    @property
    def attrs(self) -> zarr.attrs.Attributes:
        """Store-wide metadata (task name, goal pose, workspace, ...): the root group's attrs."""
        return self._root.attrs

    def __len__(self) -> int:
        return self.n_episodes

    def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
        for i in range(self.n_episodes):
            yield self.episode(i)

    def __repr__(self) -> str:
        return f"EpisodeStore({str(self.path)!r}, mode={self.mode!r}, episodes={self.n_episodes}, steps={self.n_steps}, fields={self.fields})"

    def _index(self, i: int) -> int:
        if not -self.n_episodes <= i < self.n_episodes:
            raise IndexError(
                f"episode {i} out of range: the store has {self.n_episodes} episodes (valid: {-self.n_episodes}..{self.n_episodes - 1})"
            )
        return i % self.n_episodes

    def episode_slice(self, i: int) -> slice:
        """Rows of episode ``i`` (negative ``i`` counts from the end) in the concatenated arrays."""
        i = self._index(i)
        return slice(int(self._ends[i - 1]) if i else 0, int(self._ends[i]))

    def episode(self, i: int) -> dict[str, np.ndarray]:
        """Every field of episode ``i`` as ``{name: array [T, ...]}``, checked against the episode's checksums."""
        i = self._index(i)
        rows = self.episode_slice(i)
        values = {name: read(self._data[name], rows, str(self.path), name) for name in self.fields}
        for name, v in values.items():
            self._verify(name, v, i, i + 1)
        return values

    def episode_attrs(self, i: int) -> dict[str, Any]:
        """The attrs given to :meth:`add_episode` for episode ``i`` (``{}`` if none)."""
        i = self._index(i)
        listed = self._meta.attrs.get(_EPISODE_ATTRS, [])
        return dict(listed[i]) if i < len(listed) else {}

    def field(self, name: str) -> np.ndarray:
        """The committed rows of field ``name``, all episodes concatenated, loaded into memory and checked against
        every episode's checksum."""
        if name not in self.fields:
            raise KeyError(f"no field {name!r} in {self.path}; fields: {self.fields}")
        values = read(self._data[name], slice(0, self.n_steps), str(self.path), name)
        self._verify(name, values, 0, self.n_episodes)
        return values

    @property
    def sealed(self) -> bool:
        """Whether the store records its fields and every episode's checksums, so that reads are verified (False for
        stores written before kpflow recorded them and for foreign ones; ``kpflow-verify seal=true``)."""
        return self._schema is not None

    def _verify(self, name: str, values: np.ndarray, first: int, stop: int) -> None:
        """Raise ``ValueError`` naming the field and the first episode whose rows differ from what was written, for
        ``values``: the rows of field ``name`` of episodes ``first .. stop - 1``, as read (stores without checksums are
        not verified). One pass: the episodes' joined digests (:func:`episode_digests`) are compared with the record
        at once."""
        if self._schema is None:
            return
        start = int(self._ends[first - 1]) if first else 0  # the first row of ``values`` in the store
        got = episode_digests(values, (self._ends[first:stop] - start).tolist())
        want = self._digests[name][_DIGEST * first : _DIGEST * stop]
        if got != want:
            i = first + next(
                k
                for k in range(stop - first)
                if got[_DIGEST * k : _DIGEST * (k + 1)] != want[_DIGEST * k : _DIGEST * (k + 1)]
            )
            raise ValueError(
                f"{self.path}: field {name!r} of episode {i} does not match the checksum recorded when it was written: "
                "the data on disk has changed (damaged or edited chunks)"
            )

    def verify(self, progress: bool = False) -> dict[str, Any]:
        """Read every field of every episode and check it (module docstring); returns ``{"episodes", "steps",
        "fields", "sealed"}``. Raises ``ValueError`` naming the first field and episode that differ from what was
        written, or a chunk that does not decode; a store without checksums is read whole (every chunk decodes, no
        NaN or inf) but its values cannot be checked (``sealed`` False)."""
        for _ in self._read_whole(progress):
            pass
        return self._report()

    def _report(self) -> dict[str, Any]:
        return {"episodes": self.n_episodes, "steps": self.n_steps, "fields": list(self.fields), "sealed": self.sealed}

    def _read_whole(self, progress: bool) -> Iterator[tuple[str, np.ndarray]]:
        """Each field read whole (:meth:`field`: checked against the record, if any) and refused if it holds NaN or
        inf, naming the episode."""
        from tqdm import tqdm

        for name in tqdm(self.fields, desc=f"verify {self.path.name}", unit="field", disable=not progress):
            values = self.field(name)
            if values.dtype.kind == "f" and not np.isfinite(values).all():
                row = int(np.flatnonzero(~np.isfinite(values.reshape(len(values), -1)).all(1))[0])
                episode = int(np.searchsorted(self._ends, row, side="right"))
                raise ValueError(f"{self.path}: field {name!r} of episode {episode} holds NaN or inf (row {row})")
            yield name, values

    def seal(self, progress: bool = False) -> dict[str, Any]:
        """Record the fields and every episode's checksums of a store that has none (one written before kpflow
        recorded them), reading it whole once (what :meth:`verify` checks); mode ``"a"`` only. A sealed store is only
        verified. Returns :meth:`verify`'s report."""
        if self.mode != "a" or self._lock is None:
            raise PermissionError(f"{self.path} must be open with mode='a' to seal it")
        if self.sealed:
            return self.verify(progress)
        ends = self._ends.tolist()
        sums = {name: episode_digests(values, ends).hex() for name, values in self._read_whole(progress)}
        attrs = dict(self._meta.attrs.asdict())
        attrs[_FIELDS] = _schema({name: self._data[name] for name in self.fields})
        attrs[_CHECKSUMS] = sums
        self._meta.attrs.put(attrs)  # one .zattrs write: sealed whole or not at all
        self._schema, self._digests = attrs[_FIELDS], _digests(sums, str(self.path))
        return self._report()

    # ----------------------------------------------------------------------------------------- writing

    def add_episode(self, episode: Mapping[str, np.ndarray], attrs: Mapping[str, Any] | None = None) -> int:
        """Append one episode and commit it; returns its index.

        Args:
            episode: ``{field: array [T, ...]}``, all with the same length ``T >= 1``. The first episode
                fixes the fields, their trailing shapes and dtypes; later ones must match (values are
                cast within the same dtype kind, e.g. float64 -> float32).
            attrs: optional JSON-serialisable per-episode metadata (seed, success, ...); see :meth:`episode_attrs`.

        Raises:
            PermissionError: the store is open read-only.
            ValueError: the episode or attrs do not fit the store; nothing is written.
        """
        if self.mode == "r":
            raise PermissionError(f"{self.path} is open read-only (mode='r'); open it with mode='a' to add episodes")
        values = self._validate(episode)
        if attrs is not None:
            try:
                json.dumps(dict(attrs))
            except (TypeError, ValueError) as e:
                raise ValueError(f"episode attrs must be JSON-serialisable: {e}") from e

        if self._lock is None:
            raise PermissionError(f"{self.path} was closed; open it again with mode='a' to add episodes")
        if not self.sealed and self.n_episodes:
            raise ValueError(
                f"{self.path} holds {self.n_episodes} episodes written without checksums (by an earlier kpflow, or another "
                f"tool): record them first with `kpflow-verify seal=true store={self.path}`, then append"
            )
        start = self.n_steps
        end = start + len(next(iter(values.values())))
        mark = dict(self._meta.attrs.asdict())  # 1. the write-ahead mark (with the episode's attrs): one .zattrs write
        mark[_PENDING] = {"episode": self.n_episodes, "start": start, "end": end}
        listed = mark.get(_EPISODE_ATTRS)
        if attrs is not None or listed is not None:  # per-episode attrs, kept as long as the episode count
            listed = list(listed or [])[: self.n_episodes]
            mark[_EPISODE_ATTRS] = listed + [{}] * (self.n_episodes - len(listed)) + [dict(attrs or {})]
        mark[_FIELDS] = self._schema or _schema(values)
        earlier = mark.get(_CHECKSUMS) or {}
        mark[_CHECKSUMS] = {
            name: earlier.get(name, "")[: _HEX * self.n_episodes] + episode_digests(v, [len(v)]).hex()
            for name, v in values.items()
        }
        self._meta.attrs.put(mark)
        if not self.fields:
            for name, v in values.items():
                chunks = (_chunk_rows(v[0].nbytes), *v.shape[1:])
                self._data.create(
                    name,
                    shape=(0, *v.shape[1:]),
                    chunks=chunks,
                    dtype=v.dtype,
                    compressor=_COMPRESSOR,
                    fill_value=0,
                    overwrite=True,
                )
        for name, v in values.items():  # 2. data rows (invisible until committed)
            array = self._data[name]
            array.resize((end, *array.shape[1:]))
            array[start:end] = v
        self._commit(end)  # 3. the commit point
        del mark[_PENDING]
        self._meta.attrs.put(mark)
        self._schema, self._digests = mark[_FIELDS], _digests(mark[_CHECKSUMS], str(self.path))
        return self.n_episodes - 1

    def _commit(self, end: int) -> None:
        """Append ``end`` to ``meta/episode_ends``: from here on the new episode exists."""
        self._ends_array.append(np.array([end], dtype=np.int64))
        self._ends = np.append(self._ends, np.int64(end))

    def _validate(self, episode: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Check ``episode`` against the store's fields; return its arrays in the stored dtypes."""
        values = _episode_arrays(episode)
        if self.fields:
            values = self._as_stored(values)
        for name, v in values.items():
            if v.dtype.kind == "f" and not np.isfinite(v).all():
                raise ValueError(f"field {name!r} contains NaN or inf")
        return values

    def _as_stored(self, values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``values`` with exactly the store's fields, trailing shapes and (castable) dtypes, cast to those dtypes."""
        fields = self.fields
        missing, extra = sorted(set(fields) - set(values)), sorted(set(values) - set(fields))
        if missing:
            raise ValueError(f"missing field(s) {missing}; the store's fields are {fields}")
        if extra:
            raise ValueError(f"extra field(s) {extra} not in the store; its fields are {fields}")
        out = {}
        for name in fields:
            array, v = self._data[name], values[name]
            if v.shape[1:] != array.shape[1:]:
                raise ValueError(f"field {name!r} has trailing shape {v.shape[1:]}; the store has {array.shape[1:]}")
            if not np.can_cast(v.dtype, array.dtype, casting="same_kind"):
                raise ValueError(
                    f"field {name!r} has dtype {v.dtype}, which does not cast to the store's {array.dtype}"
                )
            out[name] = v.astype(array.dtype, copy=False)
        return out


def _acquire(path: Path, wait: float | None) -> FileLock:
    """The store's exclusive write lock, waiting up to ``wait`` seconds (None: for ever)."""
    path.mkdir(parents=True, exist_ok=True)

    def say(holder: int | None) -> None:
        if wait != 0:
            print(f"waiting for process {holder or '?'} to finish writing {path} ...", file=sys.stderr, flush=True)

    try:
        return FileLock(path / LOCK_NAME, wait=wait, on_wait=say)
    except TimeoutError as e:
        raise TimeoutError(
            f"{path} cannot be opened for writing: {e} (EpisodeStore(..., wait=SECONDS | None))"
        ) from None


def _remove_partials(path: Path) -> None:
    """Remove the ``.<key>.<uuid>.partial`` temporaries that zarr's DirectoryStore leaves when killed mid-write
    (only ever called with the write lock held, so no live writer owns them)."""
    for leftover in path.rglob(".*.partial"):
        leftover.unlink(missing_ok=True)


def _episode_arrays(episode: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``episode``'s fields as arrays, checked: string names without '/', numeric or bool arrays with one shared,
    non-zero leading length T."""
    if not isinstance(episode, Mapping) or not episode:
        raise ValueError("empty episode: expected a non-empty dict {field: array [T, ...]}")
    values = {}
    for name, value in episode.items():
        if not isinstance(name, str) or not name or "/" in name:
            raise ValueError(f"field name {name!r} must be a non-empty string without '/'")
        v = np.asarray(value)
        if v.ndim == 0:
            raise ValueError(f"field {name!r} is a scalar; expected an array [T, ...] with a leading time axis")
        if v.dtype.kind not in DTYPE_KINDS or v.dtype.itemsize > 8:
            raise ValueError(
                f"field {name!r} has dtype {v.dtype}; only bool, integer and float arrays of at most 8 bytes are stored"
            )
        values[name] = v
    lengths = {name: len(v) for name, v in values.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"length mismatch: fields must share the leading length T; got {lengths}")
    if not next(iter(lengths.values())):
        raise ValueError(f"empty episode: length T = 0 (fields {sorted(values)})")
    return values
