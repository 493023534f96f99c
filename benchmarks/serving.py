"""Latency of the policy server against the same policy's ``act`` in process, one torch thread.

Run::

    python benchmarks/serving.py [--checkpoint release/pusht_standard_kcfm_human.ckpt] [--requests 200] [--steps 10]
                                 [--clients 1 4] [--out outputs/benchmarks/serving.md]

The released Push-T K-CFM answers random Push-T observations: first in process (``Deployment.make_policy().act``),
then through :class:`~kpflow.serving.server.PolicyServer` over loopback with 1 and 4 clients at once, each client
sending ``--requests`` requests one after the other. Percentiles of the round trip (client send to reply decoded)
in ms, the overhead of the median over the in-process median, and the requests per second of all clients together.
"""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from kpflow.serving import PolicyClient, PolicyServer, load_deployment  # noqa: E402
from kpflow.tasks.pusht.task import PushTTask
from kpflow.utils.io import publish  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def observations(n: int) -> list[dict]:
    rng = np.random.default_rng(0)
    return [{"keypoints": rng.uniform(100, 400, (25, 2))} for _ in range(n)]


def in_process(deployment, obs: list[dict]) -> list[float]:
    policy = deployment.make_policy()
    policy.reset(0)
    times = []
    for o in obs:
        start = time.perf_counter()
        policy.act(o)
        times.append(1e3 * (time.perf_counter() - start))
    return times


def served(uri: str, obs: list[dict], clients: int) -> tuple[list[float], float]:
    times: list[float] = []

    def drive(c: int) -> None:
        with PolicyClient(uri) as client:
            client.reset(c)
            for o in obs:
                start = time.perf_counter()
                client.act(o)
                times.append(1e3 * (time.perf_counter() - start))

    threads = [threading.Thread(target=drive, args=(c,)) for c in range(clients)]
    start = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return times, len(times) / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default=str(ROOT / "release" / "pusht_standard_kcfm_human.ckpt"))
    parser.add_argument("--requests", type=int, default=200)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--out", default=str(ROOT / "outputs" / "benchmarks" / "serving.md"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    deployment = load_deployment(args.checkpoint, PushTTask(), steps=args.steps)
    obs = observations(args.requests)
    in_process(deployment, obs[:10])  # warm-up
    base = in_process(deployment, obs)
    q = lambda x: [float(v) for v in np.percentile(x, [50, 90, 99])]  # noqa: E731
    lines = [f"# Policy server latency ({Path(args.checkpoint).name}, {args.steps} flow steps, {args.requests} requests per client, one torch thread)", "",
             "| path | clients | p50 ms | p90 ms | p99 ms | p50 / in-process p50 | requests/s |", "|---|---|---|---|---|---|---|",
             "| in-process `act()` | 1 | {:.1f} | {:.1f} | {:.1f} | 1.00 | {:.0f} |".format(*q(base), 1e3 / np.mean(base))]  # fmt: skip
    with PolicyServer(deployment, port=0).running() as uri:
        served(uri, obs[:10], 1)  # warm-up
        for clients in args.clients:
            times, rate = served(uri, obs, clients)
            p = q(times)
            lines.append(f"| websocket server, loopback | {clients} | {p[0]:.1f} | {p[1]:.1f} | {p[2]:.1f} | {p[0] / q(base)[0]:.2f} | {rate:.0f} |")
    lines += ["", "Several clients share the server's CPU: their requests queue behind each other's inference (requests/s is all clients together)."]
    publish(args.out, lines)


if __name__ == "__main__":
    main()
