"""Release a trained policy: its checkpoint reduced to what deployment needs, small enough to commit.

    python -m kpflow.release outputs/pusht_kcfm/<run>/checkpoints/last.ckpt release/<name>.ckpt [--note "..."]
    python -m kpflow.release <run>/checkpoints/last.ckpt release/suite_lift_kcfm.ckpt --ema-only \
        --task lift --source-store <generate run>/d0/rigid/episodes.zarr --source-episodes 200 --source-every 2

The released file holds the weights and buffers (``state_dict``: the trained and the EMA network, or with
``--ema-only`` the EMA network alone, which is what sampling uses), the normalisation statistics, the plain hyper-parameters and a ``release`` record (source path, note,
parameter count) and nothing else: no optimiser, scheduler or loop state. It is written atomically, and only after it
has loaded back through :func:`kpflow.load_policy` (``torch.load(weights_only=True)``).

With ``--source-store``, the transported K-CFM's source index is written beside it
(:func:`~kpflow.policies.factory.source_index_path`): the keypoints of every ``--source-every``-th step of the
store's first ``--source-episodes`` episodes, searched as ``--task``'s transporting policies search by default
(robot keypoints weighted 4, relative to the objects). A transported K-CFM uses the sources' keypoints only, so their
chunks are kept one action long.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from kpflow.utils.checkpoint import read_checkpoint
from kpflow.utils.errors import command
from kpflow.utils.io import atomic_path

KEEP = ("state_dict", "hyper_parameters", "pytorch-lightning_version")


def release(src: str | Path, dst: str | Path, note: str = "", ema_only: bool = False) -> Path:
    """Write the deployment part of checkpoint ``src`` to ``dst`` (module docstring); returns ``dst``."""
    checkpoint = read_checkpoint(src)
    out = {k: checkpoint[k] for k in KEEP if k in checkpoint}
    state = out["state_dict"]
    if ema_only:
        state = {k: v for k, v in state.items() if not k.startswith("net.")}
    out["state_dict"] = state
    weights = sum(v.numel() for k, v in state.items() if k.startswith("ema_net."))
    out["release"] = {"source": str(src), "note": str(note), "ema_parameters": int(weights), "ema_only": ema_only}
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    from kpflow import load_policy

    with atomic_path(dst) as tmp:
        torch.save(out, tmp)
        load_policy(tmp)  # a file that does not load back never reaches dst
    return dst


def release_source_index(dst: str | Path, task_name: str, store: str | Path, episodes: int, every: int = 1) -> Path:
    """Write the source index of a transported K-CFM released at ``dst`` (module docstring); returns its path."""
    from kpflow.data.episode_store import EpisodeStore
    from kpflow.data.source_index import SourceIndex
    from kpflow.policies.factory import frame_indices, source_index_path
    from kpflow.tasks.suite.task import SuiteTask

    layout = SuiteTask(task_name).policy_layout
    with EpisodeStore(store) as s:
        full = SourceIndex.from_store(s, 1, None, None, range(min(episodes, s.n_episodes)), "keypoints", "ee_target")
    keep = slice(None, None, int(every))
    index = SourceIndex(full.keypoints[keep], full.chunks[keep], layout.weights({"robot": 4.0}), frame_indices(layout, "objects"))
    return index.save(source_index_path(dst))


@command
def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("src", help="a K-CFM Lightning checkpoint")
    parser.add_argument("dst", help="where to write the released checkpoint (e.g. release/<name>.ckpt)")
    parser.add_argument("--note", default="", help="what the checkpoint is (stored in it)")
    parser.add_argument("--ema-only", action="store_true", help="keep the EMA network alone (what sampling uses)")
    parser.add_argument("--task", help="a robosuite task (lift, stack, can, square): its source index layout")
    parser.add_argument("--source-store", help="the training store: write the transported K-CFM's source index beside dst")
    parser.add_argument("--source-episodes", type=int, default=200, help="its first episodes (the ones trained on)")
    parser.add_argument("--source-every", type=int, default=1, help="keep every k-th step")
    args = parser.parse_args(argv)
    if args.source_store and not args.task:
        raise ValueError("--source-store needs --task (the layout its index is searched with)")
    dst = release(args.src, args.dst, args.note, args.ema_only)
    print(f"released {dst} ({dst.stat().st_size / 1e6:.2f} MB)")
    if args.source_store:
        index = release_source_index(dst, args.task, args.source_store, args.source_episodes, args.source_every)
        print(f"source index {index} ({index.stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
