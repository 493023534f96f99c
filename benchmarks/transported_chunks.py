"""How far the chunks of transported K-CFM variants are from the demonstrated ones (the measurement behind
:mod:`kpflow.policies.transported_kcfm`'s choice to pull back only the robot).

Run::

    python benchmarks/transported_chunks.py --checkpoint outputs/pusht_kcfm/kcfm_200/checkpoints/last.ckpt \
        [--store data/pusht_expert_200.zarr] [--index-episodes 180] [--queries 120]

The source index holds the first ``--index-episodes`` episodes of the store; ``--queries`` states of the remaining
episodes (seeded) are the observations. For each, every variant acts once and the mean distance of its first 8
targets to the 8 demonstrated ones is recorded; the table gives the median and the 90th percentile (px), and is
written atomically to ``--out``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import datetime  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from kpflow.data.episode_store import EpisodeStore  # noqa: E402
from kpflow.data.source_index import SourceIndex  # noqa: E402
from kpflow.maps import AffineMap, GPMap, ILWRMap  # noqa: E402
from kpflow.policies.chunk_transport import TransportPolicy  # noqa: E402
from kpflow.policies.kcfm.model import KCFM  # noqa: E402
from kpflow.policies.kcfm.policy import KCFMPolicy  # noqa: E402
from kpflow.policies.transported_kcfm import TransportedKCFMPolicy  # noqa: E402
from kpflow.tasks.pusht.geometry import PUSHT_BLOCK, pusht_weights  # noqa: E402
from kpflow.tasks.pusht.task import PushTTask  # noqa: E402
from kpflow.utils.checkpoint import load_checkpoint  # noqa: E402
from kpflow.utils.io import publish  # noqa: E402

PUSHT = PushTTask.policy_layout  # the transporting policies need the task's layout (Push-T: the agent is the robot)

EXECUTE = 8


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--store", default="data/pusht_expert_200.zarr")
    parser.add_argument("--index-episodes", type=int, default=180)
    parser.add_argument("--queries", type=int, default=120)
    parser.add_argument("--out", default="outputs/benchmarks/transported_chunks.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    store = EpisodeStore(args.store)
    if not 0 < args.index_episodes < len(store):
        raise ValueError(f"--index-episodes must be in 1..{len(store) - 1}, got {args.index_episodes}")
    weights = pusht_weights(agent=4.0)
    index = SourceIndex.from_store(store, 20, weights, PUSHT_BLOCK, episodes=range(args.index_episodes))
    held_out = SourceIndex.from_store(store, 20, weights, PUSHT_BLOCK, episodes=range(args.index_episodes, len(store)))
    model = load_checkpoint(KCFM, args.checkpoint)
    variants = {
        "policy transportation (ILWR)": TransportPolicy(index, ILWRMap, EXECUTE, layout=PUSHT),
        "K-CFM at the observation": KCFMPolicy(model, 10, EXECUTE),
        "transported K-CFM, all keypoints pulled back (ILWR)": TransportedKCFMPolicy(
            model, index, ILWRMap, 10, EXECUTE, "all", layout=PUSHT
        ),
        "transported K-CFM, all keypoints pulled back (GP)": TransportedKCFMPolicy(
            model, index, GPMap, 10, EXECUTE, "all", layout=PUSHT
        ),
        "transported K-CFM, robot pulled back (ILWR)": TransportedKCFMPolicy(
            model, index, ILWRMap, 10, EXECUTE, "agent", layout=PUSHT
        ),
        "transported K-CFM, robot pulled back (GP)": TransportedKCFMPolicy(
            model, index, GPMap, 10, EXECUTE, "agent", layout=PUSHT
        ),
        "transported K-CFM, rigid map": TransportedKCFMPolicy(
            model, index, AffineMap, 10, EXECUTE, "agent", layout=PUSHT
        ),
    }
    rows = np.random.default_rng(0).choice(len(held_out), min(args.queries, len(held_out)), replace=False)
    errors = {name: [] for name in variants}
    for k in rows:
        obs = {"keypoints": held_out.keypoints[k].astype(np.float64)}
        truth = held_out.chunks[k, :EXECUTE].astype(np.float64)
        for name, policy in variants.items():
            policy.reset(int(k))
            errors[name].append(float(np.linalg.norm(policy.act(obs) - truth, axis=-1).mean()))
    lines = [
        f"## Chunk error of transported K-CFM variants ({len(rows)} states of {len(store) - args.index_episodes} "
        f"episodes held out of a {args.index_episodes}-episode source index)",
        "",
        "| variant | median (px) | p90 (px) |",
        "|---|---|---|",
        *(f"| {name} | {np.median(e):.1f} | {np.percentile(e, 90):.1f} |" for name, e in errors.items()),
        "",
        f"Mean distance of the first {EXECUTE} targets to the demonstrated ones. Checkpoint {args.checkpoint}; "
        f"{datetime.date.today()}, torch {torch.__version__}, one thread.",
    ]
    return publish(args.out, lines)


if __name__ == "__main__":
    main()
