"""Merge the shards of a generation run: ``kpflow-merge 'shards=multirun/generate/lift/NAME/*' out=FOLDER``.

A generation run split into shards (``kpflow-generate -m ... shards=S 'shard=range(S)'``, :mod:`kpflow.cli.generate`)
leaves one folder per shard. This joins them into ``out``, the folder one unsharded run writes
(:func:`kpflow.generation.generate.merge_shards`): per variant and family the episodes in attempt order, the same to the
bit, the robomimic export if the shards had one, ``results.json`` and ``results.md`` over all the attempts, and the
resolved config. ``shards`` is a list of folders (``'shards=[A,B]'``) or a glob (``'shards=DIR/*'``: the folders it
matches; quote it, so that the shell passes it on). The shards must be of one run (the same settings and seed, each
shard once, none missing) and finished; anything else is refused with an error naming the folders, before anything
is written. ``out`` must not exist; it is written in a temporary folder beside it and renamed into place at the end.
"""

from __future__ import annotations

import glob
from pathlib import Path

import hydra
from omegaconf import DictConfig, ListConfig

from kpflow.generation.generate import merge_shards
from kpflow.utils.config_checks import Key, check_config
from kpflow.utils.errors import command, config_dir_checked

KEYS = {"out": Key(str), "progress": Key(bool)}
GLOB = set("*?[")


def shard_folders(shards) -> list[Path]:
    """The folders ``shards`` names: each entry (a list, or one string) a folder, or a glob expanded to the folders
    it matches (sorted; files such as a sweep's ``multirun.yaml`` are skipped). ``ValueError`` for an entry that is
    not a string, a glob that matches no folder, or a folder that holds run folders (a sweep's) rather than being one."""
    entries = list(shards) if isinstance(shards, (ListConfig, list, tuple)) else [shards]
    folders = []
    for entry in entries:
        if not isinstance(entry, str) or not entry:
            raise ValueError(f"config key shards must be a folder, a glob or a list of them; got {entry!r}")
        if GLOB & set(entry):
            matched = sorted(Path(p) for p in glob.glob(entry) if Path(p).is_dir())
            if not matched:
                raise ValueError(f"shards={entry} matches no folder")
            folders += matched
        elif not (Path(entry) / "generation.json").exists() and list(Path(entry).glob("*/generation.json")):
            raise ValueError(f"{entry} holds run folders (a sweep's?), it is not one: give them as 'shards={entry}/*'")
        else:
            folders.append(Path(entry))
    return folders


@config_dir_checked
@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="merge")
@command
def main(cfg: DictConfig) -> dict:
    check_config(cfg, KEYS)
    folders = shard_folders(cfg.shards)
    results = merge_shards(folders, cfg.out, cfg.progress)
    for row in results["summary"]:
        print(f"{results['task']} {row['variant']} {row['family']}: {row['successes']}/{row['trials']} generated")
    print(f"merged {len(folders)} shards into {cfg.out}")
    return results


if __name__ == "__main__":
    main()
