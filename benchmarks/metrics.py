"""Benchmark of kpflow's curve metrics (discrete Fréchet, DTW) against the textbook double loop, on one CPU thread.

Run::

    python benchmarks/metrics.py [--sizes 50 200 500] [--repeats 5] [--out PATH]

The markdown table is printed and written atomically to ``--out`` (default ``outputs/benchmarks/metrics.md``).

What is timed: one call of :func:`kpflow.eval.metrics.discrete_frechet` and of :func:`kpflow.eval.metrics.dtw` on two
random 2-D curves of T points each (float32, as the experiments pass them), after one untimed warm-up call. kpflow
sweeps the anti-diagonals of the coupling matrix as tensor operations; the baseline, measured in the same run on the
same curves, fills ``c[i, j] = combine(d[i, j], min(c[i-1, j], c[i-1, j-1], c[i, j-1]))`` cell by cell over a numpy
distance matrix (Eiter & Mannila 1994 for Fréchet; the same recursion with a sum for DTW). The table gives medians
over ``--repeats`` calls, their ratio, and the largest disagreement between the two (a check, not a timing).
Target: the 200-point pair in under 50 ms per metric (the experiments score thousands of trajectories).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy and torch are imported

import argparse
import datetime
import platform
import statistics
import time

import numpy as np
import torch

from kpflow.eval.metrics import discrete_frechet, dtw
from kpflow.utils.io import publish

TARGET_MS = 50.0  # per metric, 200 points


def loop_coupling(a: np.ndarray, b: np.ndarray, combine) -> float:
    """The textbook O(T S) recursion, one cell at a time (the baseline)."""
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    T, S = d.shape
    c = np.full((T, S), np.inf)
    for i in range(T):
        for j in range(S):
            if i == 0 and j == 0:
                c[i, j] = d[0, 0]
                continue
            best = min(
                c[i - 1, j] if i else np.inf, c[i, j - 1] if j else np.inf, c[i - 1, j - 1] if i and j else np.inf
            )
            c[i, j] = combine(d[i, j], best)
    return float(c[-1, -1])


def median_ms(fn, repeats: int) -> tuple[float, float]:
    value = fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - start))
    return statistics.median(times), float(value)


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[50, 200, 500])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default="outputs/benchmarks/metrics.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)

    rows = [
        "| metric | points | kpflow ms (median) | double loop ms (median) | speed-up | max disagreement |",
        "|---|---|---|---|---|---|",
    ]
    verdicts = []
    for n in args.sizes:
        a, b = torch.randn(n, 2, generator=g), torch.randn(n, 2, generator=g)
        an, bn = a.double().numpy(), b.double().numpy()
        for name, metric, combine in (("discrete Fréchet", discrete_frechet, max), ("DTW", dtw, lambda x, y: x + y)):
            ours, value = median_ms(lambda: metric(a, b), args.repeats)
            base, reference = median_ms(lambda: loop_coupling(an, bn, combine), max(1, args.repeats // 2))
            error = abs(value - reference) / max(1.0, abs(reference))
            rows.append(f"| {name} | {n} | {ours:.2f} | {base:.1f} | {base / ours:.1f}x | {error:.1e} |")
            if n == 200:
                verdicts.append(
                    f"{name}, 200 points: {ours:.1f} ms < {TARGET_MS:.0f} ms: {'PASS' if ours < TARGET_MS else 'MISS'}"
                )
    lines = ["## Curve metrics", "", *rows, "", "Targets:", *[f"- {v}" for v in verdicts], ""]
    lines.append(
        f"{datetime.date.today()}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores, one thread."
    )
    return publish(args.out, lines)


if __name__ == "__main__":
    main()
