"""One episode store from several: :func:`merge_stores` copies the episodes of source stores into a new store, in a
chosen order (store by store, or by an episode attribute such as a generation attempt's ``index``), with their
per-episode attrs; :func:`combine_stores` makes one dataset of parts of different stores (the first episodes of
each, the fields they share, their provenance recorded).

The copy is exact: every episode is read through :meth:`~kpflow.data.episode_store.EpisodeStore.episode` (checked
against its checksums, for sealed stores) and appended as it is stored, in the same dtypes, so the new store holds the
same bytes a single writer appending the same episodes in the same order writes. The sources must agree on their
fields (names, dtypes, trailing shapes) and their store-wide attrs; nothing is cast. The new store is written in a
temporary folder beside ``out`` and renamed into place (:func:`~kpflow.utils.io.atomic_dir`): it appears whole or not
at all, and an existing ``out`` is refused before anything is written.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any, Sequence

from ..utils.io import atomic_dir
from .episode_store import EpisodeStore


def episode_order(stores: Sequence[EpisodeStore], key: str) -> list[tuple[int, int]]:
    """``(store, episode)`` numbers of every episode of ``stores``, sorted by the episode attribute ``key``. Raises
    ``ValueError`` naming the store and episode when an episode has no such attribute, or two share a value (the
    stores overlap)."""
    entries = []
    for s, store in enumerate(stores):
        for e in range(store.n_episodes):
            value = store.episode_attrs(e).get(key)
            if value is None:
                raise ValueError(f"{store.path}: episode {e} has no attribute {key!r} to order the merge by")
            entries.append((value, s, e))
    try:
        entries.sort(key=lambda entry: entry[0])
    except TypeError:
        raise ValueError(
            f"the episodes' {key!r} attributes are not comparable: {sorted({type(v).__name__ for v, *_ in entries})}"
        ) from None
    for (a, s, e), (b, t, f) in zip(entries, entries[1:]):
        if a == b:
            raise ValueError(
                f"{key} {a!r} is held twice: by episode {e} of {stores[s].path} and episode {f} of {stores[t].path}"
            )
    return [(s, e) for _, s, e in entries]


def _layout(store: EpisodeStore) -> dict[str, tuple[str, tuple]] | None:
    """Each field's dtype and trailing shape (from the first episode), None for an empty store."""
    if not store.n_episodes:
        return None
    return {name: (v.dtype.str, v.shape[1:]) for name, v in store.episode(0).items()}


def _store_attrs(store: EpisodeStore) -> dict[str, Any]:
    return dict(store.attrs.asdict())


def merge_stores(out: str | Path, sources: Sequence[str | Path], key: str | None = None,
                 order: Sequence[tuple[int, int]] | None = None) -> Path:  # fmt: skip
    """Write the episodes of the stores ``sources`` into a new store ``out`` (module docstring) and return ``out``.

    Args:
        out: the new store's folder; must not exist.
        sources: the stores to copy from (opened read-only).
        key: order the episodes by this episode attribute (:func:`episode_order`); with neither ``key`` nor
            ``order``, store by store in the order of ``sources``.
        order: ``(source, episode)`` numbers to copy, in order (instead of ``key``).

    Raises:
        FileExistsError: ``out`` exists.
        ValueError: the sources' fields or store attrs differ, the order names an episode twice or one that does not
            exist, or a source is damaged (nothing is written).
    """
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists already: the merged store needs a new folder")
    if key is not None and order is not None:
        raise ValueError("give key or order, not both")
    with contextlib.ExitStack() as stack:
        stores = [stack.enter_context(EpisodeStore(p)) for p in sources]
        _check_compatible(stores)
        if order is None:
            order = (
                episode_order(stores, key)
                if key is not None
                else [(s, e) for s, st in enumerate(stores) for e in range(st.n_episodes)]
            )
        order = [(int(s), int(e)) for s, e in order]
        if len(set(order)) != len(order):
            raise ValueError("the merge order names an episode twice")
        for s, e in order:
            if not (0 <= s < len(stores) and 0 <= e < stores[s].n_episodes):
                raise ValueError(f"the merge order names episode {e} of source {s}, which does not exist")
        with atomic_dir(out) as tmp, EpisodeStore(tmp, mode="a") as merged:
            attrs = _store_attrs(stores[0]) if stores else {}
            if attrs:
                merged.attrs.put(attrs)
            for s, e in order:
                merged.add_episode(stores[s].episode(e), attrs=stores[s].episode_attrs(e) or None)
    return out


def _check_compatible(stores: Sequence[EpisodeStore]) -> None:
    """Raise ``ValueError`` naming two stores whose fields (names, dtypes, trailing shapes) or store attrs differ."""
    first_attrs = None
    layouts = []
    for store in stores:
        attrs = _store_attrs(store)
        if first_attrs is None:
            first_attrs = (store, attrs)
        elif attrs != first_attrs[1]:
            keys = sorted(k for k in set(attrs) | set(first_attrs[1]) if attrs.get(k) != first_attrs[1].get(k))
            raise ValueError(
                f"{first_attrs[0].path} and {store.path} hold different store attrs ({', '.join(keys)}): not parts of one store"
            )
        layout = _layout(store)
        if layout is not None:
            layouts.append((store, layout))
    for (a, la), (b, lb) in zip(layouts, layouts[1:]):
        if la != lb:
            names = sorted(n for n in set(la) | set(lb) if la.get(n) != lb.get(n))
            what = "; ".join(
                f"{n}: {la.get(n, 'absent')} in {a.path}, {lb.get(n, 'absent')} in {b.path}" for n in names
            )
            raise ValueError(f"the stores' fields differ ({what}): they cannot be merged without casting")


def combine_stores(
    out: str | Path, sources: Sequence[tuple[str | Path, int | None]], fields: Sequence[str] | None = None
) -> Path:
    """Write a new store ``out`` of the first ``n`` episodes (None: all) of each ``(store, n)`` of ``sources`` in turn
    (e.g. 90 human demonstrations and a policy's self-generated ones), holding ``fields`` (None: the fields every
    source has). Each episode keeps its attrs and gains ``source`` (its store's place in ``sources``) and
    ``source_episode``; the store's attrs record ``combined_from``: each source's path, episode count and attrs.

    Raises:
        FileExistsError: ``out`` exists.
        ValueError: a source asked for more episodes than it holds, a field missing from a source or stored with
            another dtype or trailing shape, or no field in common (nothing is written).
    """
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists already: the combined store needs a new folder")
    with contextlib.ExitStack() as stack:
        stores = [(stack.enter_context(EpisodeStore(p)), n) for p, n in sources]
        for store, n in stores:
            if n is not None and not 0 <= int(n) <= store.n_episodes:
                raise ValueError(f"{store.path} holds {store.n_episodes} episodes; {n} asked for")
        layouts = [(store, _layout(store)) for store, _ in stores if store.n_episodes]
        if fields is None:
            fields = sorted(set.intersection(*(set(layout) for _, layout in layouts))) if layouts else []
        if not fields:
            raise ValueError(f"the stores {[str(s.path) for s, _ in stores]} have no field in common to combine")
        for name in fields:
            kinds = {str(store.path): layout.get(name) for store, layout in layouts}
            if None in kinds.values():
                raise ValueError(f"field {name!r} is missing from {[p for p, k in kinds.items() if k is None]}")
            if len(set(kinds.values())) > 1:
                raise ValueError(
                    f"field {name!r} is stored differently: "
                    + "; ".join(f"{k[0]} {k[1]} in {p}" for p, k in kinds.items())
                )
        provenance = [
            {
                "path": str(store.path),
                "episodes": store.n_episodes if n is None else int(n),
                "attrs": _store_attrs(store),
            }
            for store, n in stores
        ]
        with atomic_dir(out) as tmp, EpisodeStore(tmp, mode="a") as combined:
            combined.attrs.put({"combined_from": provenance})
            for s, (store, n) in enumerate(stores):
                for e in range(store.n_episodes if n is None else int(n)):
                    episode = store.episode(e)
                    attrs = {**(store.episode_attrs(e) or {}), "source": s, "source_episode": e}
                    combined.add_episode({name: episode[name] for name in fields}, attrs=attrs)
    return out
