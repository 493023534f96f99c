"""What a generation run has committed, so that a killed run resumes where it stopped (:mod:`.generation`).

The run folder holds ``generation.json`` (:func:`run_manifest`: what decides its attempts, written when the run
starts) and one folder per cell (a variant and a family), ``<variant>/<family>/``, with

* ``attempts.jsonl``: every attempt's record, one JSON line each, in attempt order (attempt ``i`` on line ``i``),
  each written with one ``write`` and fsync'ed before the next attempt is committed;
* ``episodes.zarr``: the successes' episodes in attempt order (:class:`~kpflow.data.episode_store.EpisodeStore`,
  attrs ``variant, index, family, source``).

An attempt is committed by its journal line and, if it succeeded, then by its episode: the store's append is a
success's commit point. So a kill leaves the cell's attempts ``0..k-1`` committed and at most one more partly
written: the last line torn (no final newline), or the last line a success whose episode the store does not hold
(the store drops its own uncommitted append). :meth:`CellJournal.committed` drops that attempt and returns the
others; anything else (a line that is not the next attempt's record, a store whose episodes are not the journal's
successes) is refused with an error naming the file, and the journal is left as it was. Like the store's, this
protects against a killed or crashed process, not against power loss (the store is not fsync'ed).

Shards. A run may do one shard of the attempts (``shards`` > 1): shard ``k`` of ``S`` runs the attempts ``i`` with
``i % S == k`` (:func:`shard_indices`), so its cells' journals hold those, in order (line ``j`` records attempt
``k + j * S``), and its ``generation.json`` records ``shards`` and ``shard`` (an unsharded run's records neither, so
it is what it always was). :func:`read_shards` checks that folders are the complete, finished shards of one run, and
:meth:`CellJournal.finished` reads a finished cell without changing anything, for
:func:`kpflow.generation.generate.merge_shards`.
"""

from __future__ import annotations

import functools
import json
import os
from pathlib import Path
from typing import Any, Sequence

from kpflow.data.episode_store import EpisodeStore
from kpflow.utils.io import write_json, write_text

MANIFEST = "generation.json"
JOURNAL = "attempts.jsonl"
STORE = "episodes.zarr"
#: what the journal reads of an attempt's record (:meth:`kpflow.generation.generate.Generator.attempt`)
RECORD_KEYS = ("variant", "index", "family", "source", "success", "failure")
#: what a stored episode's attrs repeat of its record
EPISODE_ATTRS = ("variant", "index", "family", "source")


def _plain(value: Any) -> Any:
    """``value`` as JSON: callables by their qualified name, ``functools.partial`` with its arguments, containers
    element by element, anything else JSON does not hold by its ``repr``."""
    if isinstance(value, functools.partial):
        return {"partial": _plain(value.func), "args": _plain(list(value.args)), "keywords": _plain(value.keywords)}
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if callable(value) and hasattr(value, "__qualname__"):
        return f"{value.__module__}.{value.__qualname__}"
    return repr(value)


def run_manifest(task, families: dict, variants: list[str], n: int, n_sources: int, seed: int, candidates: int | None,
                 stop_early: bool, shards: int = 1, shard: int = 0) -> dict:  # fmt: skip
    """What decides a generation run's attempts (as JSON): the task, variants, each family's transport (its
    attributes), ``n``, ``n_sources``, ``seed``, ``candidates`` and ``stop_early``, and for one shard of a run
    (``shards`` > 1) ``shards`` and ``shard``. Workers, videos and the export are not in it: they change no
    attempt."""
    manifest = _plain({
        "task": task.name, "variants": list(variants), "families": {name: vars(t) for name, t in families.items()},
        "n": n, "n_sources": n_sources, "seed": seed, "candidates": candidates, "stop_early": stop_early,
    })  # fmt: skip
    if shards > 1:
        manifest.update(shards=shards, shard=shard)
    return manifest


def shard_indices(n: int, shards: int = 1, shard: int = 0) -> range:
    """The attempt indices shard ``shard`` of ``shards`` runs in each cell: ``i`` in ``0..n-1`` with
    ``i % shards == shard`` (all of them for one shard). ``ValueError`` unless ``1 <= shards <= n`` and
    ``0 <= shard < shards``."""
    for name, value in (("n", n), ("shards", shards), ("shard", shard)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{name} must be an integer; got {value!r}")
    if not 1 <= shards <= n:
        raise ValueError(f"shards must be in 1..n = 1..{n} (every shard needs an attempt); got {shards}")
    if not 0 <= shard < shards:
        raise ValueError(f"shard must be in 0..shards-1 = 0..{shards - 1}; got {shard}")
    return range(shard, n, shards)


def unsharded(manifest: dict) -> dict:
    """``manifest`` without its shard (``shards``, ``shard``): the manifest of the whole run."""
    return {k: v for k, v in manifest.items() if k not in ("shards", "shard")}


def check_output(out: Path, manifest: dict, resume: bool) -> None:
    """Refuse an output folder this run cannot write into, before anything is written: without ``resume``, one that
    holds a generation run already (``generation.json``, ``results.json``, a cell's journal or store); with
    ``resume``, one without ``generation.json`` or whose ``generation.json`` is another run's (the message names the
    settings that differ)."""
    out = Path(out)
    path = out / MANIFEST
    if not resume:
        cells = [p for p in (*out.glob(f"*/*/{JOURNAL}"), *out.glob(f"*/*/{STORE}"))]
        used = [p for p in (path, out / "results.json") if p.exists()] + cells
        if used:
            raise FileExistsError(f"{out} already holds a generation run ({used[0]} exists): pass resume=true to continue it "
                                  "with the same settings, or choose another output folder")  # fmt: skip
        return
    if not path.exists():
        raise FileNotFoundError(f"resume=true but {path} does not exist: {out} holds no generation run to continue")
    saved = read_manifest(out)
    whole = {"shards": 1, "shard": 0}  # what an unsharded run's manifest leaves out
    what = _differences({**whole, **saved}, {**whole, **manifest}, "there", "now")
    if what:
        raise ValueError(f"{path}: resume=true continues a run with its own settings, and these differ ({what})")


def write_manifest(out: Path, manifest: dict) -> None:
    """``generation.json`` (atomically), unless it is there already (a resumed run's, :func:`check_output`)."""
    if not (Path(out) / MANIFEST).exists():
        write_json(Path(out) / MANIFEST, manifest)


def read_manifest(out: Path) -> dict:
    """``out``'s ``generation.json``; ``FileNotFoundError`` or ``ValueError`` naming it when it is missing or not a
    generation run's settings."""
    path = Path(out) / MANIFEST
    if not path.is_file():
        raise FileNotFoundError(f"{out} is not a generation run folder: {path} does not exist")
    try:
        saved = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{path} is not valid JSON ({error}): the run folder is damaged") from None
    if not isinstance(saved, dict):
        raise ValueError(f"{path} does not hold a generation run's settings: the run folder is damaged")
    return saved


def _differences(a: dict, b: dict, here: str, there: str) -> str:
    """The keys in which ``a`` and ``b`` differ, with both values (``here``: where ``a`` is, ``there``: ``b``)."""
    keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    return "; ".join(f"{k}: {json.dumps(a.get(k))} {here}, {json.dumps(b.get(k))} {there}" for k in keys)


def read_shards(folders: Sequence[str | Path]) -> tuple[dict, list[Path]]:
    """Check that ``folders`` are all the shards of one generation run, each once and each finished, and return the
    whole run's manifest (:func:`unsharded`) and the folders in shard order. Raises ``ValueError``
    (``FileNotFoundError`` for a folder that is not a run) naming the folders and the problem: a folder given twice,
    settings that differ (another task, seed, ``n``, shard count, ...), a shard given twice, shards missing, a shard
    that did not finish (no ``results.json``: it was stopped or is still running; ``resume=true`` finishes it). Its
    cells are checked by :meth:`CellJournal.finished` when they are read."""
    folders = [Path(f) for f in folders]
    if not folders:
        raise ValueError("no shard folders given")
    seen: dict[Path, Path] = {}
    for folder in folders:
        if folder.resolve() in seen:
            raise ValueError(f"{folder} is given twice (as {seen[folder.resolve()]} and {folder})")
        seen[folder.resolve()] = folder
    manifests = [read_manifest(f) for f in folders]
    settings = [{**unsharded(m), "shards": m.get("shards", 1)} for m in manifests]
    count = settings[0]["shards"]
    for folder, other in zip(folders[1:], settings[1:]):
        if other != settings[0]:
            what = _differences(settings[0], other, f"in {folders[0]}", f"in {folder}")
            raise ValueError(
                f"{folders[0]} and {folder} are not shards of one run: their settings ({MANIFEST}) differ ({what})"
            )
    by_shard: dict[int, Path] = {}
    for folder, manifest in zip(folders, manifests):
        k = manifest.get("shard", 0)
        if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k < count:
            raise ValueError(f"{folder / MANIFEST} records shard {k!r} of {count}: the run folder is damaged")
        if k in by_shard:
            raise ValueError(f"shard {k} of {count} is given twice: {by_shard[k]} and {folder}")
        by_shard[k] = folder
    missing = sorted(set(range(count)) - set(by_shard))
    if missing:
        given = ", ".join(f"{k} ({by_shard[k]})" for k in sorted(by_shard))
        raise ValueError(f"the run has {count} shards but shard(s) {missing} are missing: given {given}")
    ordered = [by_shard[k] for k in range(count)]
    for k, folder in enumerate(ordered):
        if not (folder / "results.json").is_file():
            raise ValueError(f"{folder} (shard {k} of {count}) has not finished: it has no results.json (stopped, or still "
                             "running); finish it with its command and resume=true")  # fmt: skip
    return unsharded(manifests[0]), ordered


class CellJournal:
    """One cell's journal and store (module docstring): :meth:`committed` reads what is committed; as a context
    manager it is open for :meth:`commit`, the journal for appending and the store for writing. ``indices``: the
    attempts the cell runs, in order (:func:`shard_indices`; None: ``0, 1, 2, ...``)."""

    def __init__(self, folder: str | Path, variant: str, family: str, indices: Sequence[int] | None = None):
        self.folder, self.variant, self.family = Path(folder), variant, family
        self.indices = indices
        self.journal, self.store_path = self.folder / JOURNAL, self.folder / STORE
        self._file = self._store = None
        self._next: int | None = None

    def _index(self, line: int) -> int:
        """The attempt index recorded on journal line ``line`` (from 0)."""
        return line if self.indices is None else self.indices[line]

    # ------------------------------------------------------------------------------------------ reading
    def committed(self) -> list[dict]:
        """The committed attempts' records in attempt order; an attempt a kill left partly written is dropped from
        the journal (module docstring). Raises ``ValueError`` naming the file when the cell is otherwise
        inconsistent, leaving the journal as it was."""
        lines, torn = self._lines()
        records = self._records(lines)
        stored = self._stored_indices()
        successes = [r["index"] for r in records if r["success"]]
        if stored != successes:
            if not (records and records[-1]["success"] and stored == successes[:-1]):
                raise ValueError(
                    f"{self.store_path} holds the episodes of attempts {_brief(stored)} but {self.journal} records the "
                    f"successes {_brief(successes)}: the cell is damaged (nothing was changed)"
                )
            records, lines, torn = records[:-1], lines[:-1], True  # killed between the line and the episode's commit
        if torn:
            write_text(self.journal, "".join(line + "\n" for line in lines))
        self._next = len(records)
        return records

    def finished(self) -> list[dict]:
        """The records of a finished cell, every one of its ``indices`` committed, read without changing anything (a
        merge's read). Raises ``ValueError`` naming the file when the cell is not finished (attempts missing, a line
        torn) or is inconsistent (a line not the expected attempt's record, a store whose episodes are not the
        journal's successes)."""
        if self.indices is None:
            raise ValueError("finished() needs the cell's attempt indices")
        lines, torn = self._lines()
        if torn or len(lines) < len(self.indices):
            what = (
                "ends in a partly written line"
                if torn
                else f"records {len(lines)} of the cell's {len(self.indices)} attempts"
            )
            raise ValueError(f"{self.journal} {what}: the cell is unfinished (resume=true finishes its run)")
        records = self._records(lines)
        stored = self._stored_indices(mode="r")
        successes = [r["index"] for r in records if r["success"]]
        if stored != successes:
            raise ValueError(f"{self.store_path} holds the episodes of attempts {_brief(stored)} but {self.journal} records "
                             f"the successes {_brief(successes)}: the cell is damaged or unfinished")  # fmt: skip
        return records

    def _lines(self) -> tuple[list[str], bool]:
        """The journal's complete lines and whether a torn last line follows them."""
        if not self.journal.exists():
            return [], False
        *complete, tail = self.journal.read_bytes().split(b"\n")
        try:
            return [line.decode() for line in complete], tail != b""
        except UnicodeDecodeError:
            raise ValueError(f"{self.journal} is not text: the cell is damaged (nothing was changed)") from None

    def _records(self, lines: list[str]) -> list[dict]:
        """The records on ``lines``, each checked to be the expected attempt's (:meth:`_record`)."""
        if self.indices is not None and len(lines) > len(self.indices):
            raise ValueError(f"{self.journal} holds {len(lines)} attempts, more than the {len(self.indices)} the cell runs: "
                             "the cell is damaged (nothing was changed)")  # fmt: skip
        return [self._record(i, line) for i, line in enumerate(lines)]

    def _record(self, i: int, line: str) -> dict:
        where = f"{self.journal}, line {i + 1}"
        try:
            record = json.loads(line)
        except json.JSONDecodeError as error:
            raise ValueError(
                f"{where} is not a JSON record ({error}): the cell is damaged (nothing was changed)"
            ) from None
        if (
            not isinstance(record, dict)
            or not set(RECORD_KEYS) <= set(record)
            or not isinstance(record["success"], bool)
        ):
            raise ValueError(f"{where} is not an attempt record (with {', '.join(RECORD_KEYS)}): the cell is damaged")
        expected = {"variant": self.variant, "index": self._index(i), "family": self.family}
        if any(record[k] != v for k, v in expected.items()):
            got = {k: record[k] for k in expected}
            raise ValueError(
                f"{where} records attempt {got}, not {expected}: the cell is damaged (nothing was changed)"
            )
        return record

    def _stored_indices(self, mode: str = "a") -> list[int]:
        """The attempt index of every stored episode; the store opened for writing (``mode`` ``"a"``), so that it
        finishes its own creation or drops its own uncommitted append if a kill interrupted either (and refuses
        another writer), or (``"r"``) only read."""
        if not self.store_path.exists():
            return []
        with EpisodeStore(self.store_path, mode=mode) as store:
            attrs = [store.episode_attrs(i) for i in range(store.n_episodes)]
        if any(not isinstance(a.get("index"), int) for a in attrs):
            raise ValueError(f"{self.store_path} holds an episode without its attempt's index: not a generated store")
        return [a["index"] for a in attrs]

    # ------------------------------------------------------------------------------------------ writing
    def __enter__(self) -> CellJournal:
        if self._next is None:
            raise RuntimeError(f"read {self.journal} (committed()) before committing to it")
        self.folder.mkdir(parents=True, exist_ok=True)
        self._store = EpisodeStore(self.store_path, mode="a")
        self._file = open(self.journal, "ab")
        return self

    def __exit__(self, *exc) -> None:
        self._file.close()
        self._store.close()
        self._file = self._store = None

    def commit(self, record: dict, episode: dict | None) -> None:
        """Commit the next attempt: its record's line, fsync'ed, then its episode (a success's commit point)."""
        expected = self._index(self._next) if self.indices is None or self._next < len(self.indices) else None
        if record["index"] != expected or (episode is not None) != record["success"]:
            raise ValueError(f"{self.journal}: expected attempt {expected} with an episode if it succeeded, got "
                             f"attempt {record['index']} (success {record['success']}, episode {episode is not None})")  # fmt: skip
        self._file.write((json.dumps(record, sort_keys=True) + "\n").encode())
        self._file.flush()
        os.fsync(self._file.fileno())
        if episode is not None:
            self._store.add_episode(episode, attrs={k: record[k] for k in EPISODE_ATTRS})
        self._next += 1


def _brief(indices: list[int]) -> str:
    return (
        str(indices)
        if len(indices) <= 8
        else f"[{', '.join(map(str, indices[:3]))}, ..., {indices[-1]}] ({len(indices)})"
    )
