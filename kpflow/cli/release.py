"""Release a trained policy: its checkpoint reduced to what deployment needs, small enough to commit.

    kpflow-release src=outputs/pusht_kcfm/<run>/checkpoints/last.ckpt dst=release/<name>.ckpt [note="..."] \
        [settings.steps=20 settings.reach=60 settings.turn_deg=60]
    kpflow-release src=<run>/checkpoints/last.ckpt dst=release/suite_lift_kcfm.ckpt ema_only=true kind=transported_kcfm \
        task=lift source_store=<generate run>/d0/rigid/episodes.zarr source_action_key=ee_target source_episodes=200 source_every=2

The released file holds the weights and buffers (``state_dict``: the trained and the EMA network, or with
``ema_only=true`` the EMA network alone, which is what sampling uses), the normalisation statistics, the plain hyper-parameters, a ``release`` record (source path, note,
parameter count), the policy's own settings (``settings.<name>``: :class:`~kpflow.policies.settings.PolicySettings`)
and its config (:class:`~kpflow.policies.config.PolicyConfig`: ``kind=kcfm | transported_kcfm``,
``transport.<option>`` and, with ``task=``, the task's keypoint layout): what the release's results page measured,
so that loading it with no overrides reproduces that figure (releasing a released file again keeps its settings,
config and source path and adds the ones given) and nothing else: no optimiser, scheduler or loop state. It is written atomically, and only after it
has loaded back through :func:`kpflow.load_policy` (``torch.load(weights_only=True)``).

Without a task (data of no kpflow task, e.g. a LeRobot dataset), ``robot=[<index>, ...]`` names the robot's
keypoints and the rest are the scene (:func:`robot_layout`). With ``source_store`` (or ``data=``, a data node of
``kpflow/conf/data/``, its goals read as it says), the
transported K-CFM's source index is written beside it
(:func:`~kpflow.policies.factory.source_index_path`): the keypoints of every ``source_every``-th step of the
store's first ``source_episodes`` episodes, stored with the built-in search's weights and frame (:data:`kpflow.policies.config.DEFAULTS`; the builder searches
it as the policy's resolved transport says). A transported K-CFM uses the sources' keypoints only, so their
chunks are kept one action long.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import hydra
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from kpflow.core.policy import PolicyLayout
from kpflow.policies.config import CHECKPOINT_KEY as CONFIG_KEY
from kpflow.policies.config import DEFAULTS, KINDS, PolicyConfig, TransportConfig
from kpflow.policies.settings import CHECKPOINT_KEY as SETTINGS_KEY
from kpflow.utils.checkpoint import read_checkpoint
from kpflow.utils.config_checks import Key, check_config
from kpflow.utils.errors import command, config_dir_checked
from kpflow.utils.io import atomic_path

KEEP = ("state_dict", "hyper_parameters", "pytorch-lightning_version")


def release(src: str | Path, dst: str | Path, note: str = "", ema_only: bool = False, settings: Mapping | None = None, kind: str | None = None,
            transport: Mapping | None = None, layout: PolicyLayout | None = None) -> Path:  # fmt: skip
    """Write the deployment part of checkpoint ``src`` to ``dst`` with the policy ``settings`` given (None values:
    not set), its ``kind`` and ``transport`` options and the task's keypoint ``layout`` (None: ``src``'s) on top of
    what ``src`` holds (module docstring); returns ``dst``."""
    checkpoint = read_checkpoint(src)
    out = {k: checkpoint[k] for k in KEEP if k in checkpoint}
    config = PolicyConfig.of_checkpoint(checkpoint, str(src))
    config = config.given(
        kind, TransportConfig.of({k: v for k, v in (transport or {}).items() if v is not None}), **(settings or {})
    )
    if config.kind == "kcfm" and config.transport.record():
        raise ValueError(
            f"kind=kcfm releases the K-CFM as it is: transport options {sorted(config.transport.record())} would be unused"
        )
    if layout is not None:
        config = replace(config, layout=layout.record())
    if config.settings.record():
        out[SETTINGS_KEY] = config.settings.record()
    out[CONFIG_KEY] = config.record()
    earlier = checkpoint.get("release") if isinstance(checkpoint.get("release"), dict) else {}
    state = out["state_dict"]
    if ema_only:
        state = {k: v for k, v in state.items() if not k.startswith("net.")}
    out["state_dict"] = state
    weights = sum(v.numel() for k, v in state.items() if k.startswith("ema_net."))
    out["release"] = {**earlier, "source": str(earlier.get("source", src)), "note": str(note or earlier.get("note", "")), "ema_parameters": int(weights),
                      "ema_only": bool(ema_only or earlier.get("ema_only", False))}  # fmt: skip
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    from kpflow import load_policy

    with atomic_path(dst) as tmp:
        torch.save(out, tmp)
        load_policy(
            tmp, kind="kcfm"
        )  # a file that does not load back never reaches dst (its source index is written after it)
    return dst


def release_source_index(dst: str | Path, layout, store: str | Path | None, episodes: int, every: int = 1, action_key: str = "action",
                         demos=None) -> Path:  # fmt: skip
    """Write the source index of a transported K-CFM released at ``dst`` (module docstring): over ``demos`` (a data
    node, its goals read as it says: Push-T's hindsight goals) or else the first ``episodes`` of ``store``; returns
    its path."""
    from kpflow.data.episode_store import EpisodeStore
    from kpflow.data.source_index import SourceIndex
    from kpflow.policies.factory import source_index_path
    from kpflow.policies.source_search import SourceSearch

    if demos is not None:
        full = SourceSearch().index(demos, layout, 1)
    else:
        with EpisodeStore(store) as s:
            full = SourceIndex.from_store(s, 1, None, None, range(min(episodes, s.n_episodes)), "keypoints", action_key)
    keep = slice(None, None, int(every))
    kept = SourceIndex(full.keypoints[keep], full.chunks[keep], None, None, full.episodes[keep])
    return (
        SourceSearch.of(DEFAULTS["search"]).reindexed(kept, layout).save(source_index_path(dst))
    )  # searched as the builder reindexes it


KEYS = {
    "src": Key(str),
    "dst": Key(str),
    "note": Key(str),
    "ema_only": Key(bool),
    "source_store": Key(str, nullable=True),
    "source_episodes": Key(int, lo=1),
    "source_every": Key(int, lo=1),
    "source_action_key": Key(str),
    "kind": Key(str, choices=KINDS, nullable=True),
}


def robot_layout(hparams, robot) -> PolicyLayout:
    """The keypoint layout of a checkpoint trained on data of no kpflow task: its keypoints, the ``robot`` ones (indices,
    negative from the end) in group ``robot`` and the rest in ``scene`` (role ``objects``), actions a position first:
    enough for a transported K-CFM (what it pulls back, what it fits its map on and searches relative to)."""
    k, d, a = int(hparams["n_keypoints"]), int(hparams["keypoint_dim"]), int(hparams["action_dim"])
    robot = list(robot)
    if not robot or any(not isinstance(i, int) or not -k <= i < k for i in robot):
        raise ValueError(f"robot must name the robot's keypoints by index in -{k}..{k - 1}; got {robot}")
    ours = tuple(sorted({i % k for i in robot}))
    rest = tuple(i for i in range(k) if i not in ours)
    if not rest:
        raise ValueError(f"robot={robot} names every keypoint: the scene needs some for the map to be fitted on")
    return PolicyLayout(
        k, d, a, {"scene": rest, "robot": ours}, {"objects": ("scene",), "goals": (), "robot": ("robot",)}
    )


@config_dir_checked
@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="release")
@command
def main(cfg: DictConfig) -> Path:
    check_config(cfg, KEYS)
    sources = cfg.source_store or cfg.get("data") is not None
    if cfg.get("task") is not None and cfg.robot is not None:
        raise ValueError(
            "task= and robot= both give the keypoint layout: give one (robot= is for data of no kpflow task)"
        )
    if sources and cfg.get("task") is None and cfg.robot is None:
        raise ValueError(
            "source_store and data= need the keypoint layout the index is searched with: task=<name> (kpflow/conf/task/) "
            "or, for data of no kpflow task, robot=[<index>, ...] (the robot's keypoints)"
        )
    if cfg.get("task") is not None:
        layout = instantiate(cfg.task).policy_layout
    elif cfg.robot is not None:
        layout = robot_layout(read_checkpoint(cfg.src)["hyper_parameters"], OmegaConf.to_container(cfg.robot))
    else:
        layout = None
    settings = OmegaConf.to_container(cfg.settings) if cfg.get("settings") else None
    transport = OmegaConf.to_container(cfg.transport, resolve=True) if cfg.get("transport") else None
    demos = instantiate(cfg.data) if cfg.get("data") is not None else None  # before anything is written
    dst = release(cfg.src, cfg.dst, cfg.note, cfg.ema_only, settings, cfg.kind, transport, layout)
    print(f"released {dst} ({dst.stat().st_size / 1e6:.2f} MB)")
    if sources:
        try:
            index = release_source_index(
                dst, layout, cfg.source_store, cfg.source_episodes, cfg.source_every, cfg.source_action_key, demos
            )
        except BaseException:
            dst.unlink()  # a transported release without its index is half a release
            raise
        print(f"source index {index} ({index.stat().st_size / 1e6:.2f} MB)")
    return dst


if __name__ == "__main__":
    main()
