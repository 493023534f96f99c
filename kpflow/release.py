"""Release a trained policy: its checkpoint reduced to what deployment needs, small enough to commit.

    python -m kpflow.release outputs/pusht_kcfm/<run>/checkpoints/last.ckpt release/<name>.ckpt [--note "..."]

The released file holds the weights and buffers (``state_dict``: the trained and the EMA network, the
normalisation statistics), the plain hyper-parameters and a ``release`` record (source path, note, parameter
count) and nothing else: no optimiser, scheduler or loop state. It is written atomically, and only after it has loaded back
through :func:`kpflow.load_policy` (``torch.load(weights_only=True)``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from kpflow.utils.checkpoint import read_checkpoint
from kpflow.utils.errors import command
from kpflow.utils.io import atomic_path

KEEP = ("state_dict", "hyper_parameters", "pytorch-lightning_version")


def release(src: str | Path, dst: str | Path, note: str = "") -> Path:
    """Write the deployment part of checkpoint ``src`` to ``dst`` (module docstring); returns ``dst``."""
    checkpoint = read_checkpoint(src)
    out = {k: checkpoint[k] for k in KEEP if k in checkpoint}
    weights = sum(v.numel() for k, v in out["state_dict"].items() if k.startswith("ema_net."))
    out["release"] = {"source": str(src), "note": str(note), "ema_parameters": int(weights)}
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    from kpflow import load_policy

    with atomic_path(dst) as tmp:
        torch.save(out, tmp)
        load_policy(tmp)  # a file that does not load back never reaches dst
    return dst


@command
def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("src", help="a K-CFM Lightning checkpoint")
    parser.add_argument("dst", help="where to write the released checkpoint (e.g. release/<name>.ckpt)")
    parser.add_argument("--note", default="", help="what the checkpoint is (stored in it)")
    args = parser.parse_args(argv)
    dst = release(args.src, args.dst, args.note)
    print(f"released {dst} ({dst.stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
