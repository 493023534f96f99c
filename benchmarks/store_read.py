"""Benchmark: what per-episode checksums cost when reading an episode store, on one CPU thread.

Run::

    python benchmarks/store_read.py [--stores PATH ...] [--repeats 7] [--out PATH]

The markdown table is printed and written atomically to ``--out`` (default ``outputs/benchmarks/store_read.md``).

Each store (default: the released Table 1 store and, when ``../shared/data/pusht_cchi_v7_replay.zarr`` is present,
the human Push-T dataset imported into a temporary store) is copied twice into a temporary folder: once as it is
(sealed: every read checked against the episodes' xxh3_64 checksums) and once with its field record and checksums
removed (what a store written before checksums reads like: the same code, nothing verified). Two reads are timed on
each, interleaved, medians over ``--repeats``: opening the store and reading every field whole (what training's chunk
datasets do), and opening it and reading every episode one by one (what iteration does). Both include zarr's
decompression; the ratio is checked / unchecked. Target: at most 1.10 (issue 40).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy is imported

import argparse
import datetime
import json
import platform
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from kpflow.data.episode_store import EpisodeStore
from kpflow.tasks.pusht.replay_import import import_pusht_replay
from kpflow.utils.io import publish

ROOT = Path(__file__).resolve().parents[1]
RELEASED = ROOT / "release/pusht_table1_35_corrected.zarr"
HUMAN = ROOT.parent / "shared/data/pusht_cchi_v7_replay.zarr"
TARGET = 1.10


def unsealed_copy(src: Path, dest: Path) -> Path:
    """``src`` copied to ``dest`` without its field record and checksums."""
    shutil.copytree(src, dest)
    attrs = json.loads((dest / "meta/.zattrs").read_text())
    attrs.pop("fields", None), attrs.pop("checksums", None)
    (dest / "meta/.zattrs").write_text(json.dumps(attrs))
    return dest


def read_fields(path: Path) -> None:
    store = EpisodeStore(path)
    for name in store.fields:
        store.field(name)


def read_episodes(path: Path) -> None:
    store = EpisodeStore(path)
    for i in range(store.n_episodes):
        store.episode(i)


def interleaved(fn, a: Path, b: Path, repeats: int) -> tuple[float, float]:
    """Median ms of ``fn(a)`` and ``fn(b)``, alternating, after one untimed call of each."""
    fn(a), fn(b)
    times: dict[Path, list[float]] = {a: [], b: []}
    for _ in range(repeats):
        for path in (a, b):
            start = time.perf_counter()
            fn(path)
            times[path].append(1e3 * (time.perf_counter() - start))
    return statistics.median(times[a]), statistics.median(times[b])


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--stores", nargs="*", type=Path, default=None, help="sealed episode stores (default: released + human)"
    )
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", default="outputs/benchmarks/store_read.md")
    args = parser.parse_args(argv)
    rows = [
        "| store | episodes | steps | MB on disk | read | checked ms | unchecked ms | ratio |",
        "|---|---|---|---|---|---|---|---|",
    ]
    verdicts = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        stores = args.stores
        if stores is None:
            stores = [RELEASED]
            if HUMAN.exists():
                stores.append(import_pusht_replay(HUMAN, tmp / "pusht_human.zarr", progress=False).path)
        for src in stores:
            checked = tmp / f"{src.name}.checked"
            shutil.copytree(src, checked)
            unchecked = unsealed_copy(src, tmp / f"{src.name}.unchecked")
            store = EpisodeStore(checked)
            if not store.sealed:
                raise SystemExit(f"{src} has no checksums: seal it first (kpflow-verify seal=true)")
            mb = sum(p.stat().st_size for p in checked.rglob("*") if p.is_file()) / 1e6
            for name, fn in (("every field whole", read_fields), ("every episode", read_episodes)):
                ours, base = interleaved(fn, checked, unchecked, args.repeats)
                rows.append(
                    f"| {src.name} | {store.n_episodes} | {store.n_steps} | {mb:.1f} | {name} | {ours:.1f} | {base:.1f} | {ours / base:.3f} |"
                )
                verdicts.append(
                    f"{src.name}, {name}: {ours / base:.3f} <= {TARGET}: {'PASS' if ours / base <= TARGET else 'MISS'}"
                )
    lines = ["## Reading episode stores with checksums", "", *rows, "", "Target (at most 10 % more time with checksums):",
             *[f"- {v}" for v in verdicts], ""]  # fmt: skip
    lines.append(f"{datetime.date.today()}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores, one thread; "
                 f"medians of {args.repeats} interleaved runs.")  # fmt: skip
    return publish(args.out, lines)


if __name__ == "__main__":
    main()
