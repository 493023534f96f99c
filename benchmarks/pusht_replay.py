"""How closely kpflow's Push-T physics replays the standard human demonstrations (pusht_cchi_v7_replay.zarr).

Run::

    python benchmarks/pusht_replay.py [--data PATH] [--max-episodes N] [--out PATH]

``--data`` defaults to ``../shared/data/pusht_cchi_v7_replay.zarr`` next to the repository; when it is absent the
script says so and exits with status 0. The markdown table is printed and written atomically to ``--out`` (default
``outputs/benchmarks/pusht_replay.md``). The full dataset (206 episodes, 25,650 steps) takes about a minute.

Method (:func:`kpflow.tasks.pusht.replay_import.replay_errors`): the agent's velocity is reconstructed by running its PD
law from rest at each episode's first state (the error of the reconstructed agent positions is the first column);
then from every recorded step ``t`` the recorded agent and block are set in the simulator, ``h`` recorded actions
are applied, and the block is compared with the recorded step ``t + h`` (position in px, wrapped angle in degrees).
Rows: the standard env's mass quirks (centre of gravity (0, 45), doubled bar inertia) and a physically correct
uniform T.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import datetime
import platform
import sys
import time
from pathlib import Path

import pymunk

from kpflow.tasks.pusht.replay_import import replay_errors
from kpflow.utils.io import write_text

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared/data/pusht_cchi_v7_replay.zarr"
HORIZONS = (1, 10)
VARIANTS = {  # row name: replay_errors keyword arguments
    "standard quirks": dict(physically_correct=False),
    "physically correct": dict(physically_correct=True),
}


def fmt(x: float) -> str:
    return f"{x:.2g}" if abs(x) < 0.01 else f"{x:.3g}"


def table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def replay_tables(results: dict[str, dict]) -> str:
    header = ["variant", "agent reconstruction px (median / max)"]
    header += [f"block position px after {h} step{'s' * (h > 1)} (median / p90)" for h in HORIZONS]
    header += [f"block angle deg after {h} step{'s' * (h > 1)} (median / p90)" for h in HORIZONS]
    header += ["steps", "rollouts (" + " / ".join(f"h={h}" for h in HORIZONS) + ")"]
    rows, worst = [], []
    for name, r in results.items():
        hs = r["horizons"]
        rows.append(
            [name, f"{fmt(r['agent']['median'])} / {fmt(r['agent']['max'])}"]
            + [f"{fmt(hs[h]['position_px']['median'])} / {fmt(hs[h]['position_px']['p90'])}" for h in HORIZONS]
            + [f"{fmt(hs[h]['angle_deg']['median'])} / {fmt(hs[h]['angle_deg']['p90'])}" for h in HORIZONS]
            + [str(r["n_steps"]), " / ".join(str(hs[h]["count"]) for h in HORIZONS)]
        )
        worst.append(
            [name]
            + [f"{fmt(hs[h]['position_px']['mean'])} / {fmt(hs[h]['position_px']['max'])}" for h in HORIZONS]
            + [f"{fmt(hs[h]['angle_deg']['mean'])} / {fmt(hs[h]['angle_deg']['max'])}" for h in HORIZONS]
        )
    worst_header = ["variant"] + [f"position px after {h} (mean / max)" for h in HORIZONS]
    worst_header += [f"angle deg after {h} (mean / max)" for h in HORIZONS]
    return table(header, rows) + "\n\nMeans and worst cases:\n\n" + table(worst_header, worst)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help=f"standard replay buffer (default {DEFAULT_DATA})")
    ap.add_argument("--max-episodes", type=int, default=None, help="replay only the first N episodes")
    ap.add_argument("--out", type=Path, default=Path("outputs/benchmarks/pusht_replay.md"), help="markdown output file")
    args = ap.parse_args(argv)
    if not args.data.exists():
        print(f"Push-T dataset not found at {args.data}, skipping", file=sys.stderr)
        return 0

    t_start = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t_start:6.1f} s] {msg}", file=sys.stderr, flush=True)

    results = {}
    for name, kwargs in VARIANTS.items():
        t0 = time.perf_counter()
        results[name] = replay_errors(args.data, horizons=HORIZONS, max_episodes=args.max_episodes, **kwargs)
        log(f"{name}: {time.perf_counter() - t0:.1f} s")
    first = next(iter(results.values()))
    head = (
        f"# Push-T replay of the human demonstrations\n\n"
        f"{datetime.datetime.now().isoformat(timespec='seconds')}; `{args.data}`: {first['n_episodes']} episodes, "
        f"{first['n_steps']} steps; Python {platform.python_version()}, pymunk {pymunk.version}. From every recorded "
        f"step the recorded agent (with its PD-reconstructed velocity) and block are set in the simulator, the "
        f"recorded actions are applied, and the block is compared with the recorded state h steps later. Errors of "
        f"the block are what the recorded state lacks of the simulator's (the block's velocity, bias velocity and "
        f"cached contact impulses carried across control steps while it is pushed) plus float32 rounding."
    )
    text = f"{head}\n\n{replay_tables(results)}\n\n_total run time {time.perf_counter() - t_start:.0f} s_\n"
    print(text)
    write_text(args.out, text)
    log(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
