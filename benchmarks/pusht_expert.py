"""Success and speed of the scripted Push-T expert, and the time to collect demonstrations.

Run::

    python benchmarks/pusht_expert.py [--n 200] [--workers 2] [--collect 35] [--out PATH]

For each condition (in-distribution with a random goal and with the standard fixed goal, robot outside the
training region, object outside it) the expert runs on the first ``--n`` seeded configurations of the split
(:func:`kpflow.tasks.pusht.scene.make_split`, seed 0) with a step limit of 600 (in distribution) or 1200 (OOD).
An episode succeeds when coverage reaches 0.95; the 0.85 column counts episodes that reached 0.85 within the limit
(the threshold the paper's authors used). Seconds per episode are measured inside the worker process, one thread
each. Then ``kpflow-collect``'s function collects ``--collect`` demonstrations with ``--workers``
processes and the wall time is reported. The markdown table is printed and written atomically to ``--out`` (default
``outputs/benchmarks/pusht_expert.md``). The full run takes about 5 minutes on 2 cores.
"""

from __future__ import annotations

import os

os.environ["OMP_NUM_THREADS"] = "1"

import argparse
import datetime
import multiprocessing as mp
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from kpflow.tasks.pusht.collection import collect_pusht
from kpflow.tasks.pusht.demonstrator import PushTExpert
from kpflow.tasks.pusht.env import PushTEnv
from kpflow.tasks.pusht.rollout import run_episode
from kpflow.tasks.pusht.scene import split_config
from kpflow.utils.io import publish

CONDITIONS = [  # name, split, goal, step limit, target success at 0.95
    ("in-distribution, random goal", "in_distribution", "random", 600, 0.99),
    ("in-distribution, fixed goal", "in_distribution", "fixed", 600, 0.99),
    ("robot outside training region", "robot_ood", "random", 1200, 0.95),
    ("object outside training region", "object_ood", "random", 1200, 0.95),
]


def _episode(args):
    split, goal, limit, index = args
    config = split_config(split, index, 0, goal)
    env = PushTEnv(split=split, goal=goal)
    result = run_episode(env, PushTExpert(config.workspace), config, limit, seed=index)
    return result.success, result.first_step[0.85] is not None, result.steps, result.seconds


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=200, help="configurations per condition")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--collect", type=int, default=35, help="demonstrations to collect (0: skip)")
    parser.add_argument("--out", default="outputs/benchmarks/pusht_expert.md")
    args = parser.parse_args(argv)

    rows = [
        "| condition | configs | step limit | success >= 0.95 | target | reached 0.85 | median steps (p90) | s / episode median (p90, max) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    verdicts = []
    with mp.get_context("fork").Pool(args.workers) as pool:
        for name, split, goal, limit, target in CONDITIONS:
            jobs = [(split, goal, limit, i) for i in range(args.n)]
            out = np.array(list(tqdm(pool.imap(_episode, jobs), total=args.n, desc=name, leave=False)), float)
            success, reached, steps, seconds = out.T
            rate = success.mean()
            ok = "PASS" if rate >= target else "MISS"
            verdicts.append(f"{name}: {100 * rate:.1f}% >= {100 * target:.0f}% within {limit} steps: {ok}")
            rows.append(
                f"| {name} | {args.n} | {limit} | {100 * rate:.1f}% ({int(success.sum())}) | {100 * target:.0f}% |"
                f" {100 * reached.mean():.1f}% | {np.median(steps):.0f} ({np.percentile(steps, 90):.0f}) |"
                f" {np.median(seconds):.2f} ({np.percentile(seconds, 90):.2f}, {seconds.max():.1f}) |"
            )
    lines = ["## Scripted Push-T expert", "", *rows, ""]
    if args.collect:
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            summary = collect_pusht(Path(tmp) / "demos.zarr", args.collect, workers=args.workers, progress=False)
            wall = time.perf_counter() - start
        ok = "PASS" if wall < 120 else "MISS"
        verdicts.append(
            f"collect {args.collect} demonstrations with {args.workers} workers: {wall:.1f} s < 120 s: {ok}"
        )
        lines += [
            f"Collection: {summary['episodes']} in-distribution demonstrations ({summary['successes']}/"
            f"{summary['attempts']} attempts succeeded, {summary['steps']} steps) in {wall:.1f} s wall time"
            f" with {args.workers} worker processes.",
            "",
        ]
    lines += ["Targets:", *[f"- {v}" for v in verdicts], ""]
    lines.append(
        f"{datetime.date.today()}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores,"
        f" {args.workers} worker processes with one thread each."
    )
    return publish(args.out, lines)


if __name__ == "__main__":
    main()
