"""Verify episode stores: ``kpflow-verify store=STORE`` or ``kpflow-verify 'store=[A,B]' [seal=true]``.

Opens each store (its zarr metadata checked against kpflow's allow-list, its fields against their recorded dtypes
and shapes), reads every field of every episode and checks it against the checksum recorded when the episode was
written (:meth:`kpflow.data.episode_store.EpisodeStore.verify`). Prints one line per store; exits 1 at the first
store that fails, with the field and episode that differ. A store written before kpflow recorded checksums is read
whole but reported ``unsealed``; ``seal=true`` then records its checksums (after reading it whole), so that later reads
are verified and episodes can be appended.
"""

import hydra
from omegaconf import DictConfig, ListConfig

from kpflow.data.episode_store import EpisodeStore
from kpflow.utils.config_checks import Key, check_config
from kpflow.utils.errors import command, config_dir_checked

KEYS = {"seal": Key(bool), "progress": Key(bool)}


@config_dir_checked
@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="verify")
@command
def main(cfg: DictConfig) -> int:
    check_config(cfg, KEYS)
    stores = list(cfg.store) if isinstance(cfg.store, ListConfig) else [cfg.store]
    for path in stores:
        with EpisodeStore(path, mode="a" if cfg.seal else "r") as store:
            sealed_before = store.sealed
            report = store.seal(cfg.progress) if cfg.seal else store.verify(cfg.progress)
            state = (
                "verified"
                if sealed_before
                else "sealed now"
                if store.sealed
                else "unsealed: read whole, values unverifiable (seal=true records them)"
            )
        print(
            f"{path}: {report['episodes']} episodes, {report['steps']} steps, fields {', '.join(report['fields'])}: {state}"
        )
    return 0


if __name__ == "__main__":
    main()
