"""Interactive corrections: ``kpflow-correct policy=transport data.n_episodes=35 rounds=3``.

Copies the demonstrations (``data``) into the run's output folder, then grows that copy round by round with the
scripted expert's takeovers where the policy (``policy``, rebuilt from the grown store each round) gets stuck or
leaves the training region (:func:`~kpflow.tasks.pusht.corrections.collect_corrections`). Before the first round and
after each, the policy is evaluated on ``eval_configs`` fixed configurations of ``split`` (those of
``evaluate.py``, disjoint from the corrected ones). A learned policy
(``policy=kcfm policy.checkpoint=...``) is not retrained between rounds: alternate ``correct`` (with
``data=pusht_store data.path=<last run>/episodes.zarr``) and ``train.py`` for DAgger rounds. Writes ``episodes.zarr``,
``rounds.json``, ``rounds.md`` (dataset size and success per round) and ``rounds.png`` beside the resolved config.
Train on the result with ``python train.py experiment=pusht_kcfm data=pusht_store data.path=<run>/episodes.zarr``.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from kpflow.cli.spellings import old_spellings_read
from kpflow.data.episode_store import LOCK_NAME, EpisodeStore
from kpflow.eval import plots
from kpflow.eval.policy_trial import PolicyTrial
from kpflow.eval.reports.pusht import PushTReport
from kpflow.eval.trials import cell_summary, run_trials
from kpflow.tasks.pusht.corrections import collect_corrections
from kpflow.tasks.pusht.demos import ensure_pusht_demos
from kpflow.tasks.pusht.scene import GOAL_MODES, SPLITS
from kpflow.tasks.pusht.task import PushTTask, protocol_counts
from kpflow.utils.config_checks import SEED, Key
from kpflow.utils.errors import command, config_dir_checked
from kpflow.utils.io import atomic_dir, save_figure, write_json, write_text
from kpflow.utils.run import start_run

KEYS = {
    "seed": SEED,
    "rounds": Key(int, lo=1),
    "episodes_per_round": Key(int, lo=1),
    "split": Key(str, choices=SPLITS),
    "goal": Key(str, choices=GOAL_MODES),
    "max_steps": Key(int, lo=1),
    "stuck_steps": Key(int, lo=1),
    "takeover_steps": Key(int, lo=1),
    "eval_configs": Key(int, lo=0),
    "eval_max_steps": Key(int, lo=1, nullable=True),
    "workers": Key(int, lo=1),
    "data.n_episodes": Key(int, lo=1, nullable=True),
}


def copy_store(src: str | os.PathLike, dest: str | os.PathLike) -> Path:
    """Copy an episode store folder to ``dest`` (which must not exist) through a temporary sibling folder and a
    rename, without the source's write lock file."""
    with atomic_dir(dest) as tmp:
        shutil.copytree(src, tmp, dirs_exist_ok=True, ignore=shutil.ignore_patterns(LOCK_NAME))
    return Path(dest)


def rounds_table(reports: list[dict], start_steps: int, evals: list[dict | None]) -> str:
    """Markdown table: the dataset size after each round, how the policy did on that round's corrected episodes (no
    takeover needed) and, when measured, its success on fixed evaluation configurations (``evals[0]``: before any
    correction, ``evals[r + 1]``: after round ``r``)."""

    def measured(e: dict | None) -> str:
        if e is None:
            return "-"
        lo, hi = e["ci_085"]
        return f"{100 * e['success_085']:.1f}% [{100 * lo:.1f}, {100 * hi:.1f}] of {e['episodes']}"

    lines = [
        "| round | episodes | policy alone succeeded | with takeovers | takeovers | expert steps added | dataset chunks "
        "| evaluation success @0.85 [95% CI] |",
        "|---|---|---|---|---|---|---|---|",
        f"| start | | | | | | {start_steps} | {measured(evals[0])} |",
    ]
    for r, e in zip(reports, evals[1:]):
        n = r["episodes"]
        lines.append(
            f"| {r['round']} | {n} | {r['policy_successes']}/{n} ({100 * r['policy_successes'] / n:.1f}%) "
            f"| {r['successes']}/{n} | {r['takeovers']} | {r['chunks_added']} | {r['dataset_steps']} | {measured(e)} |"
        )
    return "\n".join(lines) + "\n"


def _plot(reports: list[dict], start_steps: int, evals: list[dict | None], path: Path) -> None:
    """Dataset size (chunks) and the policy's success per round."""
    fig, axes = plots.new_figure(1, 2, size=3.6)
    ax, bx = axes[0]
    rounds = [r["round"] for r in reports]
    for a in (ax, bx):
        a.set_aspect("auto")
        a.set_xlabel("correction round")
    ax.plot([rounds[0] - 1, *rounds], [start_steps, *(r["dataset_steps"] for r in reports)], "o-")
    ax.set_ylabel("dataset size (chunks)")
    bx.plot(rounds, [100 * r["policy_successes"] / r["episodes"] for r in reports], "o-", label="policy alone")
    bx.plot(rounds, [100 * r["successes"] / r["episodes"] for r in reports], "s--", label="with takeovers")
    if evals[0] is not None:
        bx.plot([rounds[0] - 1, *rounds], [100 * e["success_085"] for e in evals], "^-", label="evaluation @0.85")
    bx.set_ylim(0, 105)
    bx.set_ylabel("success (%)")
    bx.legend(loc="lower right")
    save_figure(fig, path, dpi=110)
    plots.close(fig)


@old_spellings_read
@config_dir_checked
@hydra.main(version_base="1.3", config_path="pkg://kpflow.conf", config_name="correct")
@command
def main(cfg: DictConfig) -> list[dict]:
    out = start_run(cfg, KEYS)
    demos = {k: cfg.data[k] for k in ("path", "n_episodes", "seed", "workers")}
    start_steps = ensure_pusht_demos(**demos).n_steps
    store_path = copy_store(demos["path"], out / "episodes.zarr")

    rebuilt = "demos" in cfg.policy  # an index policy learns from the grown store; a checkpoint stays the same

    def make_policy(store: EpisodeStore):
        if not rebuilt:
            return instantiate(cfg.policy)
        grown = OmegaConf.merge(cfg.data, {"path": str(store_path), "n_episodes": None})  # the grown store as it is
        return instantiate(cfg.policy, demos=grown)

    def evaluate(label: str) -> dict | None:
        if not (cfg.eval_configs and rebuilt):
            return None
        policy = make_policy(EpisodeStore(store_path))
        trial = PolicyTrial(PushTTask(), policy, PushTReport(), label, cfg.eval_max_steps)
        n_trials, first_index = protocol_counts(cfg.eval_configs)
        results = run_trials(
            out / f"eval_{label}", trial, cfg.split, n_trials, first_index, cfg.seed, cfg.workers, videos=0
        )
        return cell_summary(results, cfg.split)

    reports, evals = [], [evaluate("start")]
    for _ in range(cfg.rounds):
        reports += collect_corrections(
            store_path,
            make_policy,
            1,
            cfg.episodes_per_round,
            cfg.split,
            cfg.goal,
            cfg.seed,
            cfg.max_steps,
            cfg.stuck_steps,
            cfg.takeover_steps,
        )
        evals.append(evaluate(f"round{reports[-1]['round']}"))
    write_json(out / "rounds.json", {"start_steps": start_steps, "rounds": reports, "evaluations": evals})
    table = rounds_table(reports, start_steps, evals)
    write_text(out / "rounds.md", table)
    _plot(reports, start_steps, evals, out / "rounds.png")
    print(table)
    print(f"corrected store: {store_path}  table: {out / 'rounds.md'}  plot: {out / 'rounds.png'}")
    return reports


if __name__ == "__main__":
    main()
