"""Success against the number of demonstrations, per policy and split: the Push-T data-efficiency figure.

Reads Push-T evaluation runs laid out as ``<root>/<policy>/<n_demos>/results.json`` (what
``python evaluate.py ... hydra.run.dir=<root>/<policy>/<n_demos>`` writes) and draws one panel per split: success
at the ``threshold`` (0.85 by default, the paper's) against the number of demonstrations on a log axis, with the
95% Wilson interval of each point. Run::

    python -m kpflow.eval.data_efficiency outputs/data_efficiency --out results/pusht_data_efficiency.png
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kpflow.eval import plots
from kpflow.tasks.pusht.scene import SPLITS
from kpflow.utils.io import save_figure, write_text

THRESHOLDS = ("085", "095")


@dataclass(frozen=True)
class Point:
    """One evaluation run: ``policy`` trained on or searching ``n_demos`` demonstrations, on ``split``."""

    policy: str
    n_demos: int
    split: str
    episodes: int
    success: float
    ci: tuple[float, float]


def _summaries(results: dict) -> dict[str, dict]:
    """split -> summary of a Push-T ``results.json``: rows of the one trial loop (:mod:`kpflow.eval.trials`), or, in
    runs written before it, a dict by split."""
    summary = results["summary"]
    return summary if isinstance(summary, dict) else {row["condition"]: row for row in summary}


def read_points(root: str | Path, threshold: str = "085") -> list[Point]:
    """Every ``<root>/<policy>/<n_demos>/results.json`` as points, one per split it holds."""
    if threshold not in THRESHOLDS:
        raise ValueError(f"threshold must be one of {THRESHOLDS}; got {threshold!r}")
    root = Path(root)
    points = []
    for path in sorted(root.glob("*/*/results.json")):
        policy, n = path.parent.parent.name, path.parent.name
        if not n.isdigit():
            raise ValueError(f"{path}: the folder above results.json must be the number of demonstrations; got {n!r}")
        for split, s in _summaries(json.loads(path.read_text())).items():
            if split in SPLITS:
                points.append(
                    Point(policy, int(n), split, s["episodes"], s[f"success_{threshold}"], tuple(s[f"ci_{threshold}"]))
                )
    if not points:
        raise FileNotFoundError(f"no <policy>/<n_demos>/results.json under {root}")
    return points


def table(points: list[Point], threshold: str = "085") -> str:
    """Markdown: one row per policy and number of demonstrations, success [95% CI] per split."""
    rows = [
        f"| policy | demonstrations | {' | '.join(SPLITS)} | configurations per split |",
        "|---|---|" + "---|" * (len(SPLITS) + 1),
    ]
    for policy, n in sorted({(p.policy, p.n_demos) for p in points}):
        cells, episodes = [], sorted({p.episodes for p in points if (p.policy, p.n_demos) == (policy, n)})
        for split in SPLITS:
            hit = [p for p in points if (p.policy, p.n_demos, p.split) == (policy, n, split)]
            cells.append(
                f"{100 * hit[0].success:.1f}% [{100 * hit[0].ci[0]:.1f}, {100 * hit[0].ci[1]:.1f}]" if hit else "-"
            )
        rows.append(f"| {policy} | {n} | {' | '.join(cells)} | {', '.join(map(str, episodes))} |")
    title = "# Push-T: success against the number of demonstrations"
    what = f"Success at coverage 0.{threshold[1:]}, 95% Wilson intervals, per split of Table 1."
    return f"{title}\n\n{what}\n\n" + "\n".join(rows) + "\n"


def plot(points: list[Point], out: str | Path, threshold: str = "085") -> Path:
    """One panel per split: success (%) against demonstrations (log axis), a line per policy with interval bars."""
    fig, axes = plots.new_figure(1, len(SPLITS), size=3.6)
    for ax, split in zip(axes[0], SPLITS):
        ax.set_aspect("auto")
        for policy in sorted({p.policy for p in points}):
            mine = sorted((p for p in points if p.policy == policy and p.split == split), key=lambda p: p.n_demos)
            if not mine:
                continue
            n = np.array([p.n_demos for p in mine])
            rate = np.array([100 * p.success for p in mine])
            ci = np.array([[100 * (p.success - p.ci[0]), 100 * (p.ci[1] - p.success)] for p in mine]).T
            ax.errorbar(n, rate, yerr=ci, marker="o", capsize=3, label=policy)
        ax.set_xscale("log")
        ns = sorted({p.n_demos for p in points})
        ax.set_xticks(ns, [str(n) for n in ns])
        ax.set_ylim(0, 102)
        ax.set_xlabel("demonstrations")
        ax.set_title(split.replace("_", " "))
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(f"success @ coverage 0.{threshold[1:]} (%), 95% CI")
    axes[0][0].legend(loc="lower right", fontsize=8)
    path = save_figure(fig, out, dpi=110)
    plots.close(fig)
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", help="folder holding <policy>/<n_demos>/results.json")
    parser.add_argument("--out", default="results/pusht_data_efficiency.png")
    parser.add_argument("--threshold", default="085", choices=THRESHOLDS)
    args = parser.parse_args(argv)
    points = read_points(args.root, args.threshold)
    print(f"figure: {plot(points, args.out, args.threshold)}")
    text = table(points, args.threshold)
    write_text(Path(args.out).with_suffix(".md"), text)
    print(text)


if __name__ == "__main__":
    main()
