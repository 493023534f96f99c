"""Import the standard human Push-T demonstrations into a kpflow :class:`~kpflow.data.episode_store.EpisodeStore`,
and measure how closely kpflow's physics replays them.

The source is Diffusion Policy's replay buffer ``pusht_cchi_v7_replay.zarr`` (zarr v2): ``data/state`` ``[N, 5]``
(agent x, y, block x, y, block angle), ``data/action`` ``[N, 2]`` (the absolute target of the agent),
``meta/episode_ends`` ``[E]``; its ``data/keypoint``, ``data/img`` and ``data/n_contacts`` are not used. Every
episode has the standard fixed goal :data:`~kpflow.tasks.pusht.scene.FIXED_GOAL` = (256, 256, pi/4).

Run::

    python -m kpflow.tasks.pusht.replay_import SOURCE DEST [--max-episodes N] [--overwrite]

Replay (:func:`replay_errors`). The agent is a kinematic body driven by a PD law of its own position, velocity and
the actions only, so its velocity at every step is reconstructed exactly by running that law from rest at the
episode's first recorded position. From each recorded step ``t`` the block is then simulated for ``h`` actions and
compared with the recorded state ``t + h``. What the recorded state lacks, and so what is left: pymunk state that
crosses control steps while the block is pushed -- its post-solve velocity (pymunk integrates positions with it
before damping 0 clears it), its bias (penetration-correction) velocity and the cached contact impulses -- plus the
float32 rounding of the recorded states. One :class:`PushTPhysics` serves every start: its ``set_state`` clears the
bias velocity, so nothing leaks from one rollout into the next (it matches a fresh instance per start to 1e-13 px).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from kpflow.data.episode_store import EpisodeStore
from kpflow.data.zarr_checks import check_chunks, open_array, open_group, read
from kpflow.geometry.angles import wrap_angle
from kpflow.tasks.pusht.geometry import observation_keypoints
from kpflow.tasks.pusht.physics import DT, KP, KV, SUBSTEPS, PushTPhysics
from kpflow.tasks.pusht.scene import FIXED_GOAL
from kpflow.tasks.pusht.workspace import WORKSPACES
from kpflow.utils.errors import command
from kpflow.utils.io import atomic_dir

#: Arrays of the standard layout that the import reads, with their trailing shapes.
REQUIRED = {
    "data/state": ((5,), "agent x, y, block x, y, block angle"),
    "data/action": ((2,), "absolute agent target x, y"),
}
FIELDS = ("keypoints", "action", "agent_pos", "block_pose", "goal_pose", "state")


# ----------------------------------------------------------------------------------------------- reading


def read_pusht_replay(
    source: str | os.PathLike, max_episodes: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read and validate a standard Push-T replay buffer.

    Returns ``state`` ``[N, 5]``, ``action`` ``[N, 2]`` (float64) and ``episode_ends`` ``[E]`` (int64), cut to the
    first ``max_episodes`` episodes (all when ``None``).

    Raises:
        FileNotFoundError: nothing at ``source``.
        ValueError: not a zarr group, a missing array, a wrong shape or dtype, bad ``meta/episode_ends``, or NaN /
            inf in the rows read; the message names ``source`` and the problem.
    """
    path = Path(source)
    if not path.exists():
        raise FileNotFoundError(f"no Push-T replay buffer at {path}")
    if max_episodes is not None and (int(max_episodes) != max_episodes or max_episodes < 1):
        raise ValueError(f"max_episodes must be a positive integer or None; got {max_episodes!r}")
    arrays = _replay_arrays(path)
    ends = _episode_ends(arrays, path)
    if max_episodes is not None:
        ends = ends[: int(max_episodes)]

    n = int(ends[-1])
    for name in ("data/state", "data/action"):
        check_chunks(arrays[name], n, str(path), name)
    state = np.asarray(read(arrays["data/state"], slice(0, n), str(path), "data/state"), dtype=np.float64)
    action = np.asarray(read(arrays["data/action"], slice(0, n), str(path), "data/action"), dtype=np.float64)
    for name, values in (("data/state", state), ("data/action", action)):
        rows = np.flatnonzero(~np.isfinite(values).all(axis=1))
        if len(rows):
            episode = int(np.searchsorted(ends, rows[0], side="right"))
            raise ValueError(
                f"{path}: {name} contains NaN or inf ({len(rows)} rows; first row {rows[0]}, episode {episode})"
            )
    return state, action, ends


def _replay_arrays(path: Path) -> dict:
    """The replay buffer's arrays (``data/state``, ``data/action``, ``meta/episode_ends``), each checked for
    presence, shape and dtype."""
    if not (path / ".zgroup").is_file():
        raise ValueError(f"{path} is not a Push-T replay buffer: not a zarr group (no .zgroup)")
    root = open_group(path, "r", "Push-T replay buffer")  # every array checked: no codec that runs code

    arrays = {}
    for name, (trailing, meaning) in {**REQUIRED, "meta/episode_ends": ((), "cumulative episode end rows")}.items():
        expected = "[" + ", ".join(["N", *map(str, trailing)]) + "]"
        if (path / name / ".zarray").is_file():
            array = open_array(root, name, str(path))
        else:
            raise ValueError(f"{path}: missing array {name} (expected {expected}: {meaning})")
        if array.ndim != 1 + len(trailing) or array.shape[1:] != trailing:
            raise ValueError(f"{path}: {name} has shape {list(array.shape)}; expected {expected} ({meaning})")
        kinds = "iu" if name == "meta/episode_ends" else "f"
        if array.dtype.kind not in kinds:
            raise ValueError(
                f"{path}: {name} has dtype {array.dtype}; expected {'an integer' if kinds == 'iu' else 'a float'} dtype"
            )
        arrays[name] = array

    return arrays


def _episode_ends(arrays: dict, path: Path) -> np.ndarray:
    """``meta/episode_ends``, checked: non-empty, strictly increasing from 0, within the rows of both data arrays."""
    n_rows = arrays["data/state"].shape[0]
    if arrays["data/action"].shape[0] != n_rows:
        raise ValueError(f"{path}: data/action has {arrays['data/action'].shape[0]} rows but data/state has {n_rows}")
    check_chunks(arrays["meta/episode_ends"], arrays["meta/episode_ends"].shape[0], str(path), "meta/episode_ends")
    ends = np.asarray(read(arrays["meta/episode_ends"], slice(None), str(path), "meta/episode_ends"), dtype=np.int64)
    if not len(ends):
        raise ValueError(f"{path}: meta/episode_ends is empty: the buffer holds no episodes")
    bad = np.flatnonzero(np.diff(np.concatenate([[0], ends])) <= 0)
    if len(bad):
        raise ValueError(
            f"{path}: meta/episode_ends is not strictly increasing from 0 at index {bad[0]} (episode lengths must be >= 1)"
        )
    if ends[-1] > n_rows:
        raise ValueError(f"{path}: meta/episode_ends[-1] = {ends[-1]} exceeds the {n_rows} rows of data/state")
    return ends


def _episodes(ends: np.ndarray):
    starts = np.concatenate([[0], ends[:-1]])
    return [(int(a), int(b)) for a, b in zip(starts, ends)]


# ----------------------------------------------------------------------------------------------- import


def episode_fields(state: np.ndarray, action: np.ndarray) -> dict[str, np.ndarray]:
    """The kpflow fields of one episode from its standard ``state`` ``[T, 5]`` and ``action`` ``[T, 2]``."""
    keypoints = np.stack([observation_keypoints(s[2:5], FIXED_GOAL, s[0:2]) for s in state])
    return {
        "keypoints": keypoints.astype(np.float32),
        "action": action.astype(np.float32),
        "agent_pos": state[:, 0:2].astype(np.float32),
        "block_pose": state[:, 2:5].astype(np.float32),
        "goal_pose": np.broadcast_to(np.asarray(FIXED_GOAL, np.float32), (len(state), 3)).copy(),
        "state": state.astype(np.float32),
    }


def _check_dest(dest: Path, source: Path, overwrite: bool) -> bool:
    """Refuse a ``dest`` that holds episodes (unless ``overwrite``), that is not an episode store, or is the source;
    returns whether there is a ``dest`` to replace (an empty folder or store, or one ``overwrite`` lets go)."""
    if dest.resolve() == source.resolve():
        raise ValueError(f"dest {dest} is the source replay buffer; choose another path")
    if not dest.exists():
        return False
    if dest.is_dir() and not any(dest.iterdir()):
        return True
    try:
        n = EpisodeStore(dest, mode="r").n_episodes
    except ValueError as e:
        raise FileExistsError(f"{dest} exists and is not an episode store; refusing to touch it ({e})") from e
    if n and not overwrite:
        raise FileExistsError(f"{dest} already holds {n} episodes; pass overwrite=True (--overwrite) to replace it")
    return True


def import_pusht_replay(
    source: str | os.PathLike,
    dest: str | os.PathLike,
    max_episodes: int | None = None,
    progress: bool = True,
    overwrite: bool = False,
) -> EpisodeStore:
    """Convert a standard Push-T replay buffer into a kpflow episode store at ``dest``.

    Per-step fields: ``keypoints`` ``[T, 25, 2]`` (block T, goal T, agent; recomputed from the state with
    :func:`~kpflow.tasks.pusht.geometry.observation_keypoints`), ``action`` ``[T, 2]``, ``agent_pos`` ``[T, 2]``,
    ``block_pose`` ``[T, 3]``, ``goal_pose`` ``[T, 3]`` (constant, the fixed goal), ``state`` ``[T, 5]`` (the
    source's, for provenance); all float32. Store attrs: ``task="pusht"``, ``source``, ``goal="fixed"``,
    ``goal_pose``, ``workspace="standard"``, ``n_source_episodes``; per-episode attrs: ``source_episode``.

    The store is built in a temporary folder next to ``dest`` and moved into place when complete, so an
    interrupted import leaves no partial store (and, with ``overwrite``, the old one intact).

    Args:
        max_episodes: import only the first ``max_episodes`` episodes.
        progress: show a tqdm bar over episodes.
        overwrite: replace a ``dest`` that already holds episodes (never a folder that is not an episode store).

    Returns:
        The new store, open read-only.

    Raises:
        FileNotFoundError, ValueError: see :func:`read_pusht_replay`.
        FileExistsError: ``dest`` holds episodes and ``overwrite`` is false, or is not an episode store, or another
            import wrote it meanwhile.
        LockHeld: another import is writing ``dest`` now (a ``TimeoutError`` naming it and its pid).
    """
    source, dest = Path(source), Path(dest)
    state, action, ends = read_pusht_replay(source, max_episodes)
    replace = _check_dest(dest, source, overwrite)

    # one import at a time into dest, and a dest that was missing is never replaced by this one (another import's)
    with atomic_dir(dest, overwrite=replace) as tmp:
        with EpisodeStore(tmp, mode="a") as store:
            store.attrs.update(
                task="pusht",
                source=str(source.resolve()),
                goal="fixed",
                goal_pose=[float(v) for v in FIXED_GOAL],
                workspace="standard",
                n_source_episodes=len(ends),
            )
            episodes = _episodes(ends)
            for i, (a, b) in enumerate(tqdm(episodes, desc="import Push-T", unit="episode", disable=not progress)):
                store.add_episode(episode_fields(state[a:b], action[a:b]), attrs={"source_episode": i})
    return EpisodeStore(dest, mode="r")


# ----------------------------------------------------------------------------------------------- replay


def agent_velocities(agent_pos0, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Agent positions and velocities at the start of each step, by the PD law from rest at ``agent_pos0``.

    The same floating-point operations as :meth:`PushTPhysics.step` (and pymunk's kinematic position update
    ``p += v dt``): per substep ``v += (KP (a - p) + KV (0 - v)) dt``, then ``p += v dt``. Returns ``pos``,
    ``vel`` ``[T, 2]``: the state before action ``t`` is applied.
    """
    px, py = float(agent_pos0[0]), float(agent_pos0[1])
    vx = vy = 0.0
    pos, vel = np.empty((len(action), 2)), np.empty((len(action), 2))
    for t, (tx, ty) in enumerate(np.asarray(action, dtype=np.float64).tolist()):
        pos[t], vel[t] = (px, py), (vx, vy)
        for _ in range(SUBSTEPS):
            vx, vy = vx + (KP * (tx - px) + KV * (0.0 - vx)) * DT, vy + (KP * (ty - py) + KV * (0.0 - vy)) * DT
            px, py = px + vx * DT, py + vy * DT
    return pos, vel


def _summary(x: np.ndarray) -> dict[str, float]:
    if not len(x):
        return {"median": float("nan"), "p90": float("nan"), "max": float("nan"), "mean": float("nan")}
    return {
        "median": float(np.median(x)),
        "p90": float(np.percentile(x, 90)),
        "max": float(x.max()),
        "mean": float(x.mean()),
    }


def replay_errors(
    source: str | os.PathLike,
    horizons=(1, 10),
    max_episodes: int | None = None,
    physically_correct: bool = False,
    progress: bool = False,
    per_step: bool = False,
) -> dict[str, Any]:
    """How closely :class:`PushTPhysics` replays a standard Push-T replay buffer.

    For every episode the agent's velocities are reconstructed (:func:`agent_velocities`); the reconstructed
    positions are compared with the recorded ones (``agent``: px, over all steps). Then from every step ``t`` with
    ``t + h`` in the episode: ``set_state(state[t, :2], state[t, 2:5], vel[t])``, apply ``action[t : t + h]`` and
    compare the block with ``state[t + h, 2:5]``: position error (px) and absolute wrapped angle error (degrees).
    One rollout of the longest horizon per start serves every horizon.

    Returns:
        ``{"physically_correct", "n_episodes", "n_steps", "agent": {median, p90, max, mean, count},
        "horizons": {h: {"count", "position_px": {median, p90, max, mean}, "angle_deg": {...}}}}``; with
        ``per_step`` each horizon also holds the arrays ``position_px_all``, ``angle_deg_all``, ``episode`` and
        ``start`` (the start step in the episode) of every rollout.

    Raises:
        FileNotFoundError, ValueError: see :func:`read_pusht_replay`; ValueError for a non-positive horizon.
    """
    hs = sorted({int(h) for h in horizons})
    if not hs or hs[0] < 1 or any(int(h) != h for h in horizons):
        raise ValueError(f"horizons must be positive integers; got {horizons!r}")
    state, action, ends = read_pusht_replay(source, max_episodes)
    workspace = WORKSPACES["standard"]
    physics = PushTPhysics(workspace, physically_correct=physically_correct)
    agent_err = []
    pos_err = {h: [] for h in hs}
    ang_err = {h: [] for h in hs}
    where = {h: [] for h in hs}
    h_max = hs[-1]
    for e, (a, b) in enumerate(tqdm(_episodes(ends), desc="replay", unit="episode", disable=not progress)):
        s, act = state[a:b], action[a:b]
        pos, vel = agent_velocities(s[0, :2], act)
        agent_err.append(np.hypot(*(pos - s[:, :2]).T))
        steps = len(s)
        for t in range(steps - 1):
            physics.set_state(s[t, :2], s[t, 2:5], vel[t])
            for k in range(1, min(h_max, steps - 1 - t) + 1):
                physics.step(act[t + k - 1])
                if k in pos_err:
                    pose, rec = physics.block_pose, s[t + k, 2:5]
                    pos_err[k].append(float(np.hypot(pose[0] - rec[0], pose[1] - rec[1])))
                    ang_err[k].append(float(np.degrees(abs(wrap_angle(pose[2] - rec[2])))))
                    where[k].append((e, t))
    agent_all = np.concatenate(agent_err)
    out: dict[str, Any] = {
        "physically_correct": bool(physically_correct),
        "n_episodes": int(len(ends)),
        "n_steps": int(ends[-1]),
        "agent": {**_summary(agent_all), "count": int(len(agent_all))},
        "horizons": {},
    }
    for h in hs:
        p, q = np.asarray(pos_err[h]), np.asarray(ang_err[h])
        entry = {"count": int(len(p)), "position_px": _summary(p), "angle_deg": _summary(q)}
        if per_step:
            w = np.asarray(where[h], dtype=np.int64).reshape(-1, 2)
            entry.update(position_px_all=p, angle_deg_all=q, episode=w[:, 0], start=w[:, 1])
        out["horizons"][h] = entry
    return out


# ----------------------------------------------------------------------------------------------- CLI


@command
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m kpflow.tasks.pusht.replay_import",
        description="Import a standard Push-T replay buffer (pusht_cchi_v7_replay.zarr) into a kpflow episode store.",
    )
    ap.add_argument("source", type=Path, help="standard replay buffer (zarr v2 folder)")
    ap.add_argument(
        "dest",
        type=Path,
        nargs="?",
        default=None,
        help="kpflow episode store to create (default: pusht_human.zarr in kpflow's data folder, where data=pusht_human reads)",
    )
    ap.add_argument("--max-episodes", type=int, default=None, help="import only the first N episodes")
    ap.add_argument("--overwrite", action="store_true", help="replace DEST if it already holds episodes")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    if args.dest is None:
        from kpflow.utils.data_dir import data_dir

        args.dest = data_dir() / "pusht_human.zarr"
        print(f"importing into {args.dest}", file=sys.stderr, flush=True)
    store = import_pusht_replay(args.source, args.dest, args.max_episodes, not args.no_progress, args.overwrite)
    print(
        f"imported {store.n_episodes} episodes ({store.n_steps} steps) from {args.source} into {args.dest}; "
        f"fields: {', '.join(store.fields)}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
