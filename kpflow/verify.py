"""Verify episode stores: ``python -m kpflow.verify STORE [STORE ...] [--seal]``.

Opens each store (its zarr metadata checked against kpflow's allow-list, its fields against their recorded dtypes
and shapes), reads every field of every episode and checks it against the checksum recorded when the episode was
written (:meth:`kpflow.data.episode_store.EpisodeStore.verify`). Prints one line per store; exits 1 at the first
store that fails, with the field and episode that differ. A store written before kpflow recorded checksums is read
whole but reported ``unsealed``; ``--seal`` then records its checksums (after reading it whole), so that later reads
are verified and episodes can be appended.
"""

from __future__ import annotations

import argparse

from kpflow.data.episode_store import EpisodeStore
from kpflow.utils.errors import command


@command
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kpflow.verify", description=__doc__.splitlines()[0])
    parser.add_argument("stores", nargs="+", help="episode store folders (zarr)")
    parser.add_argument("--seal", action="store_true", help="record the checksums of stores that have none")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    for path in args.stores:
        with EpisodeStore(path, mode="a" if args.seal else "r") as store:
            sealed_before = store.sealed
            report = store.seal(not args.no_progress) if args.seal else store.verify(not args.no_progress)
            state = "verified" if sealed_before else "sealed now" if store.sealed else "unsealed: read whole, values unverifiable (--seal records them)"
        print(f"{path}: {report['episodes']} episodes, {report['steps']} steps, fields {', '.join(report['fields'])}: {state}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
