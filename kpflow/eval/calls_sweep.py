"""Success and score against network calls per chunk: one table and one figure from evaluation runs.

Each run folder is one ``kpflow-evaluate`` run of a K-CFM (its ``config.yaml`` names ``policy.steps`` and
``policy.solver``; its ``results.json`` holds the summary per condition). Runs are grouped into curves by a label
given on the command line, one ``LABEL=GLOB`` per curve::

    python -m kpflow.eval.calls_sweep "K-CFM (teacher)=outputs/issue43/std/teacher_*_0" \\
        "reflow=outputs/issue43/std/reflow_*_0" --out outputs/issue43/sweep_tune

writes ``sweep.md`` (a row per run: label, sampler, calls, success at 0.85 and 0.95 with Wilson intervals, score,
median decision latency) and ``sweep.png`` (success at 0.95 and score against calls, a line per label and sampler).
A checkpoint that stores its own sampling settings (``policy.steps: null``) is read for them.
"""

from __future__ import annotations

import argparse
import glob
import json
from dataclasses import dataclass
from pathlib import Path

import yaml

from kpflow.eval.plots import close, new_figure
from kpflow.utils.io import publish, save_figure


@dataclass(frozen=True)
class SweepRow:
    """One evaluation run of one condition, as the sweep reads it."""

    label: str
    solver: str
    calls: int
    condition: str
    episodes: int
    success_085: float
    ci_085: tuple[float, float]
    success_095: float
    ci_095: tuple[float, float]
    score: float
    latency_ms: float
    run: str


def read_run(label: str, folder: str | Path) -> list[SweepRow]:
    """The rows of one run folder (one per condition in its ``results.json``)."""
    folder = Path(folder)
    policy = yaml.safe_load((folder / "config.yaml").read_text())["policy"]
    steps, solver = policy.get("steps"), policy.get("solver")
    if steps is None or solver is None:  # the checkpoint's own settings
        from kpflow.policies.kcfm.model import KCFM
        from kpflow.utils.checkpoint import load_checkpoint

        steps, solver = load_checkpoint(KCFM, policy["checkpoint"]).sampler(steps, solver)
    results = json.loads((folder / "results.json").read_text())
    return [
        SweepRow(
            label,
            str(solver),
            int(steps),
            s["condition"],
            int(s["episodes"]),
            s["success_085"],
            tuple(s["ci_085"]),
            s["success_095"],
            tuple(s["ci_095"]),
            s["score"],
            s["latency_ms"],
            str(folder),
        )  # fmt: skip
        for s in results["summary"]
    ]


def table(rows: list[SweepRow]) -> list[str]:
    """Markdown lines: one row per run and condition, in the order given, calls ascending within a label."""
    pct = lambda p, ci: f"{100 * p:.1f}% [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"  # noqa: E731
    return [
        "| policy | sampler | network calls | condition | episodes | success @0.85 | success @0.95 | score | latency ms (median) | run |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *[
            f"| {r.label} | {r.solver} | {r.calls} | {r.condition} | {r.episodes} | {pct(r.success_085, r.ci_085)} | {pct(r.success_095, r.ci_095)} | "
            f"{r.score:.3f} | {r.latency_ms:.1f} | `{r.run}` |"
            for r in rows
        ],  # fmt: skip
    ]


def figure(rows: list[SweepRow], path: str | Path) -> Path:
    """Success at 0.95 (with its interval) and score against network calls (log axis), a line per label and
    sampler, a panel pair per condition."""
    conditions = list(dict.fromkeys(r.condition for r in rows))
    fig, axes = new_figure(len(conditions), 2, size=3.6)
    for row_axes, condition in zip(axes, conditions):
        curves = dict.fromkeys((r.label, r.solver) for r in rows if r.condition == condition)
        for label, solver in curves:
            pts = sorted(
                (r for r in rows if (r.label, r.solver, r.condition) == (label, solver, condition)),
                key=lambda r: r.calls,
            )
            calls = [r.calls for r in pts]
            name = f"{label}, {solver}"
            line = row_axes[0].plot(calls, [100 * r.success_095 for r in pts], marker="o", lw=1.2, label=name)[0]
            row_axes[0].fill_between(
                calls,
                [100 * r.ci_095[0] for r in pts],
                [100 * r.ci_095[1] for r in pts],
                color=line.get_color(),
                alpha=0.15,
            )
            row_axes[1].plot(calls, [r.score for r in pts], marker="o", lw=1.2, color=line.get_color(), label=name)
        for ax, what in zip(row_axes, ("success @0.95 (%)", "score")):
            ax.set_aspect("auto")
            ax.set_xscale("log", base=2)
            ax.set_xlabel("network calls per chunk", fontsize=10)
            ax.set_ylabel(what, fontsize=10)
            ax.set_title(f"{condition}: {what}", fontsize=11)
            ax.tick_params(labelsize=9)
            ax.grid(alpha=0.3)
        # right of the row's score panel, outside both axes: it covers no line or interval
        row_axes[1].legend(loc="upper left", bbox_to_anchor=(1.03, 1.0), fontsize=8, frameon=False)
    save_figure(fig, path, dpi=110, bbox_inches="tight")
    close(fig)
    return Path(path)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("curves", nargs="+", help="LABEL=GLOB of run folders")
    parser.add_argument("--out", required=True, help="folder for sweep.md and sweep.png")
    args = parser.parse_args(argv)
    rows: list[SweepRow] = []
    for spec in args.curves:
        label, sep, pattern = spec.partition("=")
        folders = sorted(f for f in glob.glob(pattern) if (Path(f) / "results.json").is_file())
        if not sep or not folders:
            raise SystemExit(f"{spec!r}: need LABEL=GLOB matching finished run folders (with results.json)")
        rows += sorted((r for f in folders for r in read_run(label, f)), key=lambda r: (r.solver, r.calls))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    publish(out / "sweep.md", table(rows))
    figure(rows, out / "sweep.png")


if __name__ == "__main__":
    main()
