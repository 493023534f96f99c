"""Latency and throughput of the policy server, batching off and on, against the same policy's ``act`` in process.

Run::

    python benchmarks/serving.py [--checkpoint release/pusht_standard_kcfm_human.ckpt] [--requests 200] [--steps 10]
                                 [--clients 1 2 4] [--max-batch 8] [--max-wait-ms 2] [--threads 1] [--processes]
                                 [--out outputs/benchmarks/serving.md]

The released Push-T K-CFM answers random Push-T observations: first in process (``Deployment.make_policy().act``),
then through :class:`~kpflow.serving.server.PolicyServer` over loopback, with batching off (``max_batch=1``) and on
(:mod:`kpflow.serving.batching`), for each number of ``--clients`` at once, each client sending ``--requests``
requests one after the other. Percentiles of the round trip (client send to reply decoded) in ms, the overhead of
the median over the in-process median, the requests per second of all clients together, that rate over the same
server's rate for one client (in the same run), and the rows per forward pass of the network. The clients are threads
of this process (the server's process, sharing its interpreter lock) or, with ``--processes``, processes of their own.
"""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import multiprocessing  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from kpflow.policies.kcfm.traced import TracedNetwork  # noqa: E402
from kpflow.serving import PolicyClient, PolicyServer, load_deployment  # noqa: E402
from kpflow.serving.batching import DEFAULT_MAX_WAIT_MS  # noqa: E402
from kpflow.tasks.pusht.task import PushTTask  # noqa: E402
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


def drive(uri: str, obs: list[dict], seed: int, start=None) -> list[float]:
    """One client's round trips (ms), sent one after the other once ``start`` (a barrier) lets it go."""
    times = []
    with PolicyClient(uri) as client:
        client.reset(seed)
        if start is not None:
            start.wait()
        for o in obs:
            begin = time.perf_counter()
            client.act(o)
            times.append(1e3 * (time.perf_counter() - begin))
    return times


def _drive_process(uri, obs, seed, start, out) -> None:
    out.put(drive(uri, obs, seed, start))


def served(uri: str, obs: list[dict], clients: int, processes: bool = False) -> tuple[list[float], float]:
    """All clients' round trips (ms) and their requests per second together, from the moment all are connected."""
    if processes:
        ctx = multiprocessing.get_context("spawn")
        start, out = ctx.Barrier(clients + 1), ctx.Queue()
        workers = [ctx.Process(target=_drive_process, args=(uri, obs, c, start, out)) for c in range(clients)]
    else:
        start, results = threading.Barrier(clients + 1), []
        workers = [
            threading.Thread(target=lambda c=c: results.append(drive(uri, obs, c, start))) for c in range(clients)
        ]
    for w in workers:
        w.start()
    start.wait()
    begin = time.perf_counter()
    if processes:
        results = [out.get() for _ in workers]
    else:
        for w in workers:
            w.join()
    wall = time.perf_counter() - begin  # to the last reply (a process's exit is not timed)
    for w in workers:
        w.join()
    times = [t for r in results for t in r]
    return times, len(times) / wall


def forward_ms(net, horizon: int, action_dim: int, cond_dim: int, rows: int, reps: int = 50) -> float:
    """The median time (ms) of one forward pass of ``net`` on ``rows`` rows."""
    x, t, c = torch.randn(rows, horizon, action_dim), torch.rand(rows), torch.randn(rows, cond_dim)
    times = []
    with torch.no_grad():
        for i in range(reps + 5):
            start = time.perf_counter()
            net(x, t, c)
            times.append(1e3 * (time.perf_counter() - start))
    return float(np.median(times[5:]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default=str(ROOT / "release" / "pusht_standard_kcfm_human.ckpt"))
    parser.add_argument("--requests", type=int, default=200)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--max-batch", type=int, default=8, help="batching on: rows per forward pass")
    parser.add_argument("--max-wait-ms", type=float, default=DEFAULT_MAX_WAIT_MS)
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--processes", action="store_true", help="clients in processes of their own (default: threads)")
    parser.add_argument("--out", default=str(ROOT / "outputs" / "benchmarks" / "serving.md"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    obs = observations(args.requests)
    q = lambda x: [float(v) for v in np.percentile(x, [50, 90, 99])]  # noqa: E731
    clients_are = "processes" if args.processes else "threads of the server's process"
    lines = [f"# Policy server latency ({Path(args.checkpoint).name}, {args.steps} flow steps, {args.requests} requests per client, "
             f"{args.threads} torch thread(s), clients: {clients_are})", "",
             "| path | clients | p50 ms | p90 ms | p99 ms | p50 / in-process p50 | requests/s | x 1 client | rows / pass |",
             "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    base = None
    for max_batch in (1, args.max_batch):
        deployment = load_deployment(
            args.checkpoint, PushTTask(), {"steps": args.steps}, max_batch=max_batch, max_wait_ms=args.max_wait_ms
        )
        path = (
            f"server, batching on ({max_batch} rows, {args.max_wait_ms:g} ms)"
            if max_batch > 1
            else "server, batching off"
        )
        if base is None:
            in_process(deployment, obs[:10])  # warm-up
            base = in_process(deployment, obs)
            lines.append(
                "| in-process `act()` | 1 | {:.1f} | {:.1f} | {:.1f} | 1.00 | {:.0f} | | 1.00 |".format(
                    *q(base), 1e3 / np.mean(base)
                )
            )
        with PolicyServer(deployment, port=0).running() as uri:
            for (
                clients
            ) in args.clients:  # warm-up: the policies' traces, one per batch size met (kpflow/policies/kcfm/traced.py)
                served(uri, obs[:10], clients)
            one = None
            for clients in args.clients:
                before = deployment.network.stats() if deployment.network else None
                times, rate = served(uri, obs, clients, args.processes)
                after = deployment.network.stats() if deployment.network else None
                rows = (after["rows"] - before["rows"]) / max(after["passes"] - before["passes"], 1) if after else 1.0
                one = rate if clients == 1 else one
                ratio = f"{rate / one:.2f}" if one else ""
                p = q(times)
                lines.append(f"| {path} | {clients} | {p[0]:.1f} | {p[1]:.1f} | {p[2]:.1f} | "
                             f"{p[0] / q(base)[0]:.2f} | {rate:.0f} | {ratio} | {rows:.2f} |")  # fmt: skip
    if deployment.network is not None:  # what the network allows: the cost of a pass by its rows, traced as served
        net, meta = deployment.network.net, deployment.metadata
        traced = TracedNetwork(net)
        passes = {
            rows: forward_ms(traced, meta.horizon, meta.action_shape[1], net.cond_dim, rows) for rows in (1, 2, 4, 8)
        }
        lines += [
            "",
            "One forward pass of the traced network (median ms) by rows: "
            + ", ".join(f"{r}: {ms:.2f}" for r, ms in passes.items())
            + f". Four clients in batches of 4 rows get at most {4 * passes[1] / passes[4]:.2f} times one client's network-bound rate.",
        ]
    lines += ["", "Server: websocket over loopback. requests/s: all clients together; x 1 client: that over the same server's "
              "1-client rate in this run; rows / pass: network rows per forward pass (batching off: 1)."]  # fmt: skip
    publish(args.out, lines)


if __name__ == "__main__":
    main()
