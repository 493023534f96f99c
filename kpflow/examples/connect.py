"""Connect to a running policy server and ask it for one action chunk: ``kpflow-connect [--uri ws://127.0.0.1:8000]``
(or ``python -m kpflow.examples.connect``).

Start a server first (``kpflow-serve checkpoint=... task=null``). The client reads the server's metadata (what it
observes, the actions it returns), sends keypoints of that shape (``--keypoints FILE.npy``, or random ones in the unit
box as a smoke test) and prints the chunk. It waits up to ``--wait`` seconds for the server to come up.
"""

import argparse

import numpy as np

from kpflow.serving.client import PolicyClient
from kpflow.utils.errors import command


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="kpflow-connect", description=__doc__.splitlines()[0])
    parser.add_argument("--uri", default="ws://127.0.0.1:8000")
    parser.add_argument("--keypoints", help="an .npy file of keypoints [K, D] (or [n_obs, K, D])")
    parser.add_argument("--wait", type=float, default=60.0, help="seconds to wait for the server")
    connect(parser.parse_args(argv))


@command
def connect(args: argparse.Namespace) -> None:
    """Ask the server at ``args.uri`` for one chunk and print what it serves and returns (a failure: one line)."""
    with PolicyClient(args.uri, wait=args.wait) as policy:
        meta = policy.metadata
        print(
            f"server: {meta.policy}, observes {meta.observation}, returns {meta.action_shape} actions at {meta.control_hz:g} Hz"
        )
        ((key, shape),) = meta.observation.items()
        keypoints = np.load(args.keypoints) if args.keypoints else np.random.default_rng(0).uniform(0, 1, shape[-2:])
        obs = {key: np.broadcast_to(keypoints, shape).copy()}
        policy.reset(seed=0)
        chunk = policy.act(obs)
        print(
            f"action chunk {list(chunk.shape)} in {policy.server_ms:.1f} ms on the server; first action {np.round(chunk[0], 4).tolist()}"
        )


if __name__ == "__main__":
    main()
