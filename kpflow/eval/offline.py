"""A policy checked against held-out demonstrations, without a simulator: ``kpflow-evaluate experiment=offline
checkpoint=CKPT data.path=STORE_OR_DATASET``.

The data config splits episodes as training did (the same ``seed`` and ``val_fraction``: the held-out episodes are
the training run's validation episodes). At every ``every``-th step of each held-out episode the policy sees the
recorded observation history and returns its chunk of ``execute`` actions; the error of a decision is the mean
Euclidean distance between its actions and the recorded ones over the steps the episode still has. The report gives
the median error of the first action and of the chunk (with the 90th percentile), beside the same errors of a
baseline that repeats the action taken before the step, says in one line whether the policy beats that baseline
(``beats_baseline``: its median chunk error is below the baseline's), and plots one episode's recorded and predicted
actions.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
from tqdm import tqdm

from kpflow.data.chunks import ChunkDataModule
from kpflow.utils.io import write_json, write_text


def _errors(chunk: np.ndarray, recorded: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    n = min(len(chunk), int(mask.sum()))
    gaps = np.linalg.norm(chunk[:n] - recorded[:n], axis=-1)
    return float(gaps[0]), float(gaps.mean())


def action_names(width: int, layout: Mapping | None = None, columns: list | None = None) -> list[str]:
    """A name per action dimension for the figure: the dataset's own column names when it has one per dimension
    (a LeRobot dataset's ``features.action.names``), else the layout's (:class:`~kpflow.core.policy.PolicyLayout`'s
    record: ``x, y(, z) position``, ``rotation 0..5`` when it has one, then ``gripper``), else ``action dim i``."""
    if columns is not None and len(columns) == width and all(isinstance(c, str) and c for c in columns):
        return list(columns)
    if layout is None:
        return [f"action dim {d}" for d in range(width)]
    position = [f"{axis} position" for axis in "xyz"[: int(layout["keypoint_dim"])]]
    rotation = [f"rotation {i} (6-D)" for i in range(6)] if layout.get("rotation") else []
    rest = width - len(position) - len(rotation)
    return position + rotation + (["gripper"] if rest == 1 else [f"gripper {i}" for i in range(max(rest, 0))])


def shown_dims(names: list[str], limit: int = 4) -> list[int]:
    """The action dimensions the figure draws: at most ``limit``, the 6-D rotation's values last (x, y, z and the
    gripper of a robot arm's 10)."""
    order = sorted(range(len(names)), key=lambda d: names[d].startswith("rotation "))
    return sorted(order[:limit])


def _column_names(data: ChunkDataModule) -> list | None:
    """The action column names a LeRobot dataset declares (None for an episode store: it names fields only)."""
    from kpflow.data.lerobot_dataset import feature_name, flat_names, is_lerobot, read_info

    if not is_lerobot(data.path):
        return None
    return flat_names(read_info(data.path)["features"].get(feature_name(data.action_key), {}).get("names"))


def evaluate_offline(output_dir: str | Path, seed: int, checkpoint: str, data: ChunkDataModule, steps: int | None = None,
                     execute: int = 8, every: int = 4, progress: bool = True) -> dict:  # fmt: skip
    """Run the offline check (module docstring) of the K-CFM at ``checkpoint`` on ``data``'s held-out episodes."""
    from kpflow.eval.plots import offline_figure
    from kpflow.policies.factory import build

    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    out = Path(output_dir)
    # the bare K-CFM (no goal limit: the held-out chunks are the demonstrated ones), by the one builder
    policy = build(
        checkpoint,
        {"kind": "kcfm", "steps": steps, "execute": execute, "reach": False, "turn_deg": False},
        input_margin=None,
    )
    steps = policy.steps
    n_obs = int(policy.model.hparams.n_obs)
    data.setup()
    held_out = data.val_set if data.val_set is not None and len(data.val_set) else data.train_set
    which = "held-out" if held_out is data.val_set else "training (no episode was held out: val_fraction)"
    items = np.flatnonzero(held_out.steps % every == 0)
    rows, chunks = [], []
    for k in tqdm(items, desc="offline check", disable=not progress):
        item = held_out[int(k)]
        history = item["history"].numpy().astype(np.float64)
        policy.reset(int(k))
        obs = {"keypoints": history[-1], **({"keypoints_history": history} if n_obs > 1 else {})}
        chunk = policy.act(obs)
        recorded, mask = item["actions"].numpy(), item["mask"].numpy()
        hold = np.repeat(held_out.previous_action(int(k))[None], len(recorded), axis=0)
        rows.append(
            (int(item["episode"]), int(item["t"]), *_errors(chunk, recorded, mask), *_errors(hold, recorded, mask))
        )
        chunks.append(chunk)
    errors = np.array([r[2:] for r in rows])
    summary = {
        "episodes": len({r[0] for r in rows}), "decisions": len(rows), "split": which, "checkpoint": str(checkpoint),
        "first_action_median": float(np.median(errors[:, 0])), "chunk_median": float(np.median(errors[:, 1])),
        "chunk_p90": float(np.percentile(errors[:, 1], 90)), "hold_first_action_median": float(np.median(errors[:, 2])),
        "hold_chunk_median": float(np.median(errors[:, 3])),
    }  # fmt: skip
    summary["beats_baseline"] = summary["chunk_median"] < summary["hold_chunk_median"]
    ours, hold = summary["chunk_median"], summary["hold_chunk_median"]
    verdict = (
        f"The K-CFM beats repeating the previous action: median chunk error {ours:.4g} against {hold:.4g}."
        if summary["beats_baseline"] else
        f"**The K-CFM loses to repeating the previous action**: median chunk error {ours:.4g} against {hold:.4g}. It has "
        "learned less than holding still: train longer, or check the data (the action field, the frames) and the checkpoint."
    )  # fmt: skip
    table = (
        f"# Offline check of {checkpoint}\n\n{summary['decisions']} decisions on {summary['episodes']} {which} episodes"
        f" (every {every}th step; {steps} network calls per chunk, {execute} actions compared).\n\n"
        "| policy | first action error, median | chunk error, median | chunk error, 90th percentile |\n|---|---|---|---|\n"
        f"| K-CFM | {summary['first_action_median']:.4g} | {summary['chunk_median']:.4g} | {summary['chunk_p90']:.4g} |\n"
        f"| repeat the previous action | {summary['hold_first_action_median']:.4g} | {summary['hold_chunk_median']:.4g} |"
        f" {np.percentile(errors[:, 3], 90):.4g} |\n\n{verdict}\n"
    )
    shown = rows[0][0]  # the first held-out episode, plotted with every decision taken in it
    picked = [i for i, row in enumerate(rows) if row[0] == shown]
    recorded = held_out.episode_actions(shown)
    config = getattr(policy.model, "policy_config", None)
    names = action_names(recorded.shape[1], getattr(config, "layout", None), _column_names(data))
    figure = offline_figure(out / "offline.png", recorded, [rows[i][1] for i in picked], [chunks[i] for i in picked],
                            shown, names=names, dims=shown_dims(names))  # fmt: skip
    write_json(
        out / "results.json",
        {
            **summary,
            "rows": [dict(zip(("episode", "t", "first", "chunk", "hold_first", "hold_chunk"), r)) for r in rows],
        },
    )
    write_text(out / "results.md", table)
    metrics = {k: v for k, v in summary.items() if isinstance(v, float)}
    return {**summary, "metrics": metrics, "table": table, "figures": [figure.name]}
