"""Push-T evaluation of one policy: success per split with confidence intervals, coverage, steps, latency, videos.

Each split's configurations are the seeded :func:`~kpflow.tasks.pusht.scene.split_config` list (indices from
``first_config`` on, so evaluation configurations differ from the demonstrations' 0, 1, 2, ...). An episode runs
until coverage 0.95 or ``max_steps``; success at 0.85 means coverage reached 0.85 within the limit (the episode
would have ended there at that threshold). The ``standard`` protocol is Diffusion Policy's test protocol:
its start-state draw (:func:`~kpflow.tasks.pusht.scene.standard_config`) on seeds ``standard_first_seed``,
``standard_first_seed + 1``, ... (100000 on: LeRobot's and DP's test seeds), ``standard_episodes`` of them (500 by
default, LeRobot's count; DP used 50), the fixed goal, at most 300 steps (whatever ``max_steps`` says), the episode
ending at coverage 0.95; score = mean over episodes of max over steps of clip(coverage / 0.95, 0, 1), success =
coverage 0.95 reached.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from kpflow.eval import plots
from kpflow.eval.parallel import map_jobs
from kpflow.eval.stats import wilson_interval
from kpflow.tasks.pusht.rollout import run_episode
from kpflow.tasks.pusht.scene import SPLITS, STANDARD_FIRST_SEED
from kpflow.tasks.pusht.task import PushTTask
from kpflow.utils.io import save_figure, write_json, write_text
from kpflow.utils.video import write_video

THRESHOLDS = (0.85, 0.95)
PROTOCOLS = (*SPLITS, "standard")
STANDARD_EPISODES, STANDARD_MAX_STEPS = 500, 300  # Diffusion Policy's Push-T test protocol (LeRobot's 500 episodes)


def _max_steps(protocol: str, max_steps: int) -> int:
    return STANDARD_MAX_STEPS if protocol == "standard" else max_steps


class TimedPolicy:
    """Wraps a policy and records how long each ``act`` takes (the decision latency)."""

    def __init__(self, policy):
        self.policy, self.latencies = policy, []
        self.n_obs = getattr(policy, "n_obs", 1)  # the observation history it conditions on (run_episode reads it)

    def reset(self, seed=None):
        self.policy.reset(seed)

    def act(self, obs):
        start = time.perf_counter()
        out = self.policy.act(obs)
        self.latencies.append(time.perf_counter() - start)
        return out


_POLICY = None  # the policy of this worker process (inherited through fork)


TASK = PushTTask()


def _episode(args) -> dict:
    protocol, index, seed, max_steps = args
    config = TASK.sample_scene(protocol, index, seed)
    policy = TimedPolicy(_POLICY)
    env = TASK.make_env(protocol)
    result = run_episode(env, policy, config, max_steps, seed=index, thresholds=THRESHOLDS)
    return {
        "protocol": protocol,
        "config_index": index,
        "success_095": result.success,
        "success_085": result.first_step[0.85] is not None,
        "steps_085": result.first_step[0.85],
        "steps_095": result.first_step[0.95],
        "final_coverage": result.coverage,
        "max_coverage": result.max_coverage,
        "steps": result.steps,
        "latency_ms": 1e3 * float(np.median(policy.latencies)) if policy.latencies else float("nan"),
    }


def summarise(episodes: list[dict]) -> dict:
    """Success rates with 95% Wilson intervals, coverage, steps to success and latency of one protocol's episodes."""
    n = len(episodes)
    out = {"episodes": n}
    for th in ("085", "095"):
        k = sum(e[f"success_{th}"] for e in episodes)
        steps = [e[f"steps_{th}"] for e in episodes if e[f"success_{th}"]]
        out[f"success_{th}"] = k / n
        out[f"ci_{th}"] = wilson_interval(k, n)
        out[f"steps_{th}"] = float(np.mean(steps)) if steps else float("nan")
    out["final_coverage"] = float(np.mean([e["final_coverage"] for e in episodes]))
    out["max_coverage"] = float(np.mean([e["max_coverage"] for e in episodes]))
    out["score"] = float(np.mean([min(e["max_coverage"] / 0.95, 1.0) for e in episodes]))
    out["latency_ms"] = float(np.nanmedian([e["latency_ms"] for e in episodes]))
    return out


def table(summaries: dict[str, dict], name: str) -> str:
    rows = [
        "| policy | split | episodes | success @0.85 [95% CI] | success @0.95 [95% CI] | mean final / max coverage"
        " | steps to 0.85 / 0.95 | standard score | latency ms (median) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for protocol, s in summaries.items():
        ci85, ci95 = s["ci_085"], s["ci_095"]
        rows.append(
            f"| {name} | {protocol} | {s['episodes']} | {100 * s['success_085']:.1f}% [{100 * ci85[0]:.1f}, {100 * ci85[1]:.1f}]"
            f" | {100 * s['success_095']:.1f}% [{100 * ci95[0]:.1f}, {100 * ci95[1]:.1f}]"
            f" | {s['final_coverage']:.3f} / {s['max_coverage']:.3f} | {s['steps_085']:.0f} / {s['steps_095']:.0f}"
            f" | {s['score']:.3f} | {s['latency_ms']:.2f} |"
        )
    return "\n".join(rows)


def _plot(summaries: dict[str, dict], episodes: list[dict], name: str, path: Path) -> None:
    fig, axes = plots.new_figure(1, 2, size=4.0)
    ax, bx = axes[0]
    for a in (ax, bx):
        a.set_aspect("auto")
    names = list(summaries)
    x = np.arange(len(names))
    for offset, th in ((-0.18, "085"), (0.18, "095")):
        rate = np.array([summaries[p][f"success_{th}"] for p in names])
        ci = np.array([summaries[p][f"ci_{th}"] for p in names])
        ax.bar(x + offset, 100 * rate, 0.34, label=f"coverage >= 0.{th[1:]}")
        ax.errorbar(x + offset, 100 * rate, yerr=100 * np.abs(ci.T - rate), fmt="none", ecolor="k", capsize=3)
    ax.set_xticks(x, [p.replace("_", "\n") for p in names])
    ax.set_ylim(0, 105)
    ax.set_ylabel("success (%) with 95% CI")
    ax.set_title(name)
    ax.legend(loc="lower left")
    for p in names:
        bx.hist([e["max_coverage"] for e in episodes if e["protocol"] == p], bins=20, range=(0, 1), alpha=0.6, label=p)
    bx.set_xlabel("max coverage in the episode")
    bx.set_ylabel("episodes")
    bx.legend(loc="upper left")
    save_figure(fig, path, dpi=110)
    plots.close(fig)


def _videos(policy, episodes: list[dict], seed: int, max_steps: int, per_kind: int, out: Path) -> list[str]:
    """Re-run (deterministically) the first ``per_kind`` successes and failures of each protocol with rendering."""
    paths = []
    for protocol in dict.fromkeys(e["protocol"] for e in episodes):
        mine = [e for e in episodes if e["protocol"] == protocol]
        for kind, chosen in (("success", [e for e in mine if e["success_095"]]), ("failure", [e for e in mine if not e["success_095"]])):
            for e in chosen[:per_kind]:
                config = TASK.sample_scene(protocol, e["config_index"], seed)
                env = TASK.make_env(protocol, render_size=256, render_mode="rgb_array")
                result = run_episode(env, policy, config, _max_steps(protocol, max_steps), seed=e["config_index"], render=True)
                paths.append(str(write_video(result.frames, out / f"{protocol}_{kind}_{e['config_index']:04d}.mp4")))
    return paths


def run_pusht_experiment(
    policy,
    output_dir: str | Path,
    seed: int = 0,
    name: str = "policy",
    split: str = "all",
    n_configs: int = 200,
    first_config: int = 10_000,
    max_steps: int = 1200,
    workers: int = 2,
    videos: int = 1,
    progress: bool = True,
    standard_episodes: int = STANDARD_EPISODES,
    standard_first_seed: int = STANDARD_FIRST_SEED,
) -> dict:
    """Evaluate ``policy`` on ``split`` (one of the splits, ``standard``, or ``all`` for the three splits):
    ``n_configs`` configurations per split from index ``first_config``, or for ``standard`` ``standard_episodes``
    episodes on Diffusion Policy's seeds from ``standard_first_seed`` (module docstring).

    Writes ``results.json`` (summary and every episode), ``results.md`` (the table), ``success.png`` and up to
    ``videos`` mp4s of successes and of failures per split into ``output_dir``; returns the results with a flat
    ``metrics`` dict for loggers.
    """
    global _POLICY
    protocols = list(SPLITS) if split == "all" else [split]
    if any(p not in PROTOCOLS for p in protocols):
        raise ValueError(f"unknown split {split!r}; choose 'all' or one of {PROTOCOLS}")
    if n_configs < 1 or workers < 1 or max_steps < 1 or standard_episodes < 1:
        raise ValueError(
            f"n_configs, workers, max_steps and standard_episodes must be >= 1, got {n_configs}, {workers}, {max_steps}, {standard_episodes}"
        )
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [
        (p, (standard_first_seed if p == "standard" else first_config) + i, seed, _max_steps(p, max_steps))
        for p in protocols
        for i in range(standard_episodes if p == "standard" else n_configs)
    ]
    _POLICY = policy
    episodes = map_jobs(_episode, jobs, workers, desc=f"evaluate {name}", unit="ep", progress=progress)
    summaries = {p: summarise([e for e in episodes if e["protocol"] == p]) for p in protocols}
    md = table(summaries, name)
    _plot(summaries, episodes, name, out / "success.png")
    video_paths = _videos(policy, episodes, seed, max_steps, videos, out) if videos else []
    results = {"name": name, "summary": summaries, "episodes": episodes, "videos": video_paths}
    results["metrics"] = {f"{p}/{k}": v for p, s in summaries.items() for k, v in s.items() if isinstance(v, float)}
    write_json(out / "results.json", results)
    write_text(out / "results.md", f"# Push-T evaluation: {name}\n\n{md}\n")
    return results
