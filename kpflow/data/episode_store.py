"""Episodes on disk in the Diffusion Policy "replay buffer" zarr v2 layout.

A store is a zarr group holding

* ``data/<field>``: one array per field, the episodes concatenated along axis 0 (time);
* ``meta/episode_ends``: int64 ``[E]``, the cumulative exclusive end row of each episode.

so existing datasets such as Diffusion Policy's ``pusht_cchi_v7_replay.zarr`` open as they are.

Crash safety: :meth:`EpisodeStore.add_episode` writes the new data rows first and appends to
``meta/episode_ends`` last; that append is the commit point. Rows past ``episode_ends[-1]`` are an
uncommitted (crashed) episode: readers ignore them and mode ``"a"`` truncates them before appending.
zarr 2.18's ``DirectoryStore.__setitem__`` writes every key (chunk or ``.zarray``/``.zattrs``
metadata) to a ``*.partial`` temp file and moves it into place with ``os.replace``, so no single key is
ever half-written. Appending to ``episode_ends`` is two such writes (``Array._append_nosync`` writes
the grown ``.zarray`` then the chunk); a crash between them leaves a last entry that reads as the fill
value 0, i.e. not greater than the previous end, which is recognised as an uncommitted episode.
(This protects against a crashing process, not against power loss: nothing is fsync'ed.)
A single writer is assumed.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np
import zarr
from numcodecs import Blosc

# Same codec as the standard Push-T replay buffer.
_COMPRESSOR = Blosc(cname="zstd", clevel=5, shuffle=Blosc.BITSHUFFLE)
_MAX_CHUNK_ROWS = 1024
_TARGET_CHUNK_BYTES = 1 << 22  # keep image chunks at a few MB
_EPISODE_ATTRS = "episode_attrs"  # key of the per-episode attrs list in meta/.zattrs


def _chunk_rows(row_bytes: int) -> int:
    """Rows per chunk along time: up to 1024, fewer for large rows (images)."""
    return max(1, min(_MAX_CHUNK_ROWS, _TARGET_CHUNK_BYTES // max(row_bytes, 1)))


def _committed_ends(ends: np.ndarray, n_rows: int, where: str) -> np.ndarray:
    """The committed prefix of ``episode_ends``.

    A last entry not greater than the previous end (the fill value of a torn append) is an
    uncommitted episode and is dropped. Any other inconsistency is corruption and raises.
    """
    if len(ends) and ends[-1] <= (ends[-2] if len(ends) > 1 else 0):
        ends = ends[:-1]
    starts = np.concatenate([[0], ends[:-1]])
    bad = np.flatnonzero(ends <= starts)
    if len(bad):
        raise ValueError(f"{where}: meta/episode_ends is not strictly increasing at index {bad[0]}: {ends[: bad[0] + 1][-2:]}")
    if len(ends) and ends[-1] > n_rows:
        raise ValueError(f"{where}: meta/episode_ends[-1] = {ends[-1]} exceeds the {n_rows} rows of the shortest data array")
    return ends


class EpisodeStore:
    """Episodes of equally-named arrays, stored as zarr ``data/<field>`` + ``meta/episode_ends``.

    Args:
        path: directory of the zarr store.
        mode: ``"r"`` read-only (the store must exist) or ``"a"`` (open for appending; created if missing).

    Raises:
        FileNotFoundError: mode ``"r"`` and nothing at ``path``.
        ValueError: ``path`` is not an episode store (not a zarr group, or no ``meta/episode_ends``).
    """

    def __init__(self, path: str | Path, mode: str = "r") -> None:
        if mode not in ("r", "a"):
            raise ValueError(f"mode must be 'r' or 'a'; got {mode!r}")
        self.path, self.mode = Path(path), mode
        if self.path.exists() and not self.path.is_dir():
            raise ValueError(f"{self.path} is not an episode store: it is a file, not a zarr directory")
        is_group = (self.path / ".zgroup").is_file()
        if mode == "r" and not self.path.exists():
            raise FileNotFoundError(f"no episode store at {self.path}")
        if not is_group and (mode == "r" or any(self.path.iterdir() if self.path.exists() else ())):
            raise ValueError(f"{self.path} is not an episode store: not a zarr group (no .zgroup)")

        self._root = zarr.open_group(store=zarr.DirectoryStore(str(self.path)), mode=mode)
        if not isinstance(self._root.get("meta/episode_ends"), zarr.Array):
            self._init_layout()
        if not isinstance(self._root.get("data"), zarr.Group):
            raise ValueError(f"{self.path} is not an episode store: missing the data group")
        self._data: zarr.Group = self._root["data"]
        self._meta: zarr.Group = self._root["meta"]
        self._ends_array: zarr.Array = self._meta["episode_ends"]

        arrays = dict(self._data.arrays())
        n_rows = min((a.shape[0] for a in arrays.values()), default=0)
        self._ends = _committed_ends(np.asarray(self._ends_array[:], dtype=np.int64), n_rows, str(self.path))
        if mode == "a":
            self._drop_uncommitted(arrays)

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

    def _drop_uncommitted(self, arrays: dict[str, zarr.Array]) -> None:
        """Mode "a": remove what a crashed :meth:`add_episode` left past the last commit."""
        if len(self._ends) < self._ends_array.shape[0]:
            self._ends_array.resize(len(self._ends))
        if not len(self._ends):  # crash during the first episode: it had fixed the fields, forget them
            for name in arrays:
                del self._data[name]
        for name, array in arrays.items():
            if len(self._ends) and array.shape[0] > self.n_steps:
                array.resize((self.n_steps, *array.shape[1:]))
        listed = self._meta.attrs.get(_EPISODE_ATTRS)
        if listed is not None and len(listed) > self.n_episodes:
            self._meta.attrs[_EPISODE_ATTRS] = listed[: self.n_episodes]

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
            raise IndexError(f"episode {i} out of range: the store has {self.n_episodes} episodes (valid: {-self.n_episodes}..{self.n_episodes - 1})")
        return i % self.n_episodes

    def episode_slice(self, i: int) -> slice:
        """Rows of episode ``i`` (negative ``i`` counts from the end) in the concatenated arrays."""
        i = self._index(i)
        return slice(int(self._ends[i - 1]) if i else 0, int(self._ends[i]))

    def episode(self, i: int) -> dict[str, np.ndarray]:
        """Every field of episode ``i`` as ``{name: array [T, ...]}``."""
        rows = self.episode_slice(i)
        return {name: self._data[name][rows] for name in self.fields}

    def episode_attrs(self, i: int) -> dict[str, Any]:
        """The attrs given to :meth:`add_episode` for episode ``i`` (``{}`` if none)."""
        i = self._index(i)
        listed = self._meta.attrs.get(_EPISODE_ATTRS, [])
        return dict(listed[i]) if i < len(listed) else {}

    def field(self, name: str) -> np.ndarray:
        """The committed rows of field ``name``, all episodes concatenated, loaded into memory."""
        if name not in self.fields:
            raise KeyError(f"no field {name!r} in {self.path}; fields: {self.fields}")
        return self._data[name][: self.n_steps]

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

        start = self.n_steps
        end = start + len(next(iter(values.values())))
        if not self.fields:
            for name, v in values.items():
                chunks = (_chunk_rows(v[0].nbytes), *v.shape[1:])
                self._data.create(name, shape=(0, *v.shape[1:]), chunks=chunks, dtype=v.dtype, compressor=_COMPRESSOR, fill_value=0, overwrite=True)
        for name, v in values.items():  # 1. data rows (invisible until committed)
            array = self._data[name]
            array.resize((end, *array.shape[1:]))
            array[start:end] = v
        listed = self._meta.attrs.get(_EPISODE_ATTRS)
        if attrs is not None or listed is not None:  # 2. per-episode attrs, kept as long as the episode count
            listed = list(listed or [])[: self.n_episodes]
            listed += [{}] * (self.n_episodes - len(listed)) + [dict(attrs or {})]
            self._meta.attrs[_EPISODE_ATTRS] = listed
        self._commit(end)  # 3. the commit point
        return self.n_episodes - 1

    def _commit(self, end: int) -> None:
        """Append ``end`` to ``meta/episode_ends``: from here on the new episode exists."""
        self._ends_array.append(np.array([end], dtype=np.int64))
        self._ends = np.append(self._ends, np.int64(end))

    def _validate(self, episode: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Check ``episode`` against the store's fields; return its arrays in the stored dtypes."""
        if not isinstance(episode, Mapping) or not episode:
            raise ValueError("empty episode: expected a non-empty dict {field: array [T, ...]}")
        values = {}
        for name, value in episode.items():
            if not isinstance(name, str) or not name or "/" in name:
                raise ValueError(f"field name {name!r} must be a non-empty string without '/'")
            v = np.asarray(value)
            if v.ndim == 0:
                raise ValueError(f"field {name!r} is a scalar; expected an array [T, ...] with a leading time axis")
            if v.dtype.kind not in "biufc":
                raise ValueError(f"field {name!r} has dtype {v.dtype}; only bool and numeric arrays are stored")
            values[name] = v
        lengths = {name: len(v) for name, v in values.items()}
        if len(set(lengths.values())) > 1:
            raise ValueError(f"length mismatch: fields must share the leading length T; got {lengths}")
        if not next(iter(lengths.values())):
            raise ValueError(f"empty episode: length T = 0 (fields {sorted(values)})")

        fields = self.fields
        if fields:
            missing, extra = sorted(set(fields) - set(values)), sorted(set(values) - set(fields))
            if missing:
                raise ValueError(f"missing field(s) {missing}; the store's fields are {fields}")
            if extra:
                raise ValueError(f"extra field(s) {extra} not in the store; its fields are {fields}")
            for name in fields:
                array, v = self._data[name], values[name]
                if v.shape[1:] != array.shape[1:]:
                    raise ValueError(f"field {name!r} has trailing shape {v.shape[1:]}; the store has {array.shape[1:]}")
                if not np.can_cast(v.dtype, array.dtype, casting="same_kind"):
                    raise ValueError(f"field {name!r} has dtype {v.dtype}, which does not cast to the store's {array.dtype}")
                values[name] = v.astype(array.dtype, copy=False)
        for name, v in values.items():
            if v.dtype.kind in "fc" and not np.isfinite(v).all():
                raise ValueError(f"field {name!r} contains NaN or inf")
        return values
