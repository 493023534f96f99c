"""Episodes in robomimic's hdf5 layout, the format MimicGen writes and robomimic trains from.

::

    data                      attrs: total (samples in all), env_args (JSON: env_name, type 1 = robosuite, env_kwargs)
    data/demo_<i>             attrs: num_samples
    data/demo_<i>/actions     [T, 7]   the absolute OSC pose action and the gripper
    data/demo_<i>/states      [T, S]   MuJoCo's flattened state before each action (robomimic replays from these)
    data/demo_<i>/rewards     [T]      1 at the last step (the episode succeeded), else 0
    data/demo_<i>/dones       [T]      the same
    data/demo_<i>/obs/robot0_eef_pos  [T, 3]
    data/demo_<i>/obs/keypoints       [T, K, 3] (when the episodes have them: what kpflow's policies observe)
    mask/train                the demo names (every exported episode is a training demo)

The file is written to a temporary next to the target and renamed into place, so a reader never sees half of it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import h5py
import numpy as np

from kpflow.utils.io import atomic_path

FIELDS = ("action", "state", "ee_pos")


def export_robomimic(path: str | Path, episodes: Sequence[dict], env_name: str, env_kwargs: dict) -> Path:
    """Write ``episodes`` (each with ``action [T, 7]``, ``state [T, S]``, ``ee_pos [T, 3]``) to ``path``."""
    if not episodes:
        raise ValueError("no episodes to export")
    for i, e in enumerate(episodes):
        missing = [f for f in FIELDS if f not in e]
        if missing:
            raise ValueError(f"episode {i} lacks {missing}; an exported episode needs {FIELDS}")
        lengths = {f: len(e[f]) for f in FIELDS}
        if len(set(lengths.values())) != 1 or not lengths["action"]:
            raise ValueError(f"episode {i}'s fields differ in length or are empty: {lengths}")
    path = Path(path)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            data = f.create_group("data")
            total = 0
            names = []
            for i, e in enumerate(episodes):
                name = f"demo_{i}"
                g = data.create_group(name)
                t = len(e["action"])
                g.attrs["num_samples"] = t
                g.create_dataset("actions", data=np.asarray(e["action"], np.float64))
                g.create_dataset("states", data=np.asarray(e["state"], np.float64))
                done = np.zeros(t, np.int64)
                done[-1] = 1
                g.create_dataset("rewards", data=done.astype(np.float64))
                g.create_dataset("dones", data=done)
                obs = g.create_group("obs")
                obs.create_dataset("robot0_eef_pos", data=np.asarray(e["ee_pos"], np.float64))
                if "keypoints" in e:
                    obs.create_dataset("keypoints", data=np.asarray(e["keypoints"], np.float64))
                total += t
                names.append(name)
            data.attrs["total"] = total
            data.attrs["env_args"] = json.dumps({"env_name": env_name, "type": 1, "env_kwargs": env_kwargs})
            f.create_group("mask").create_dataset("train", data=np.array(names, dtype="S"))
    return path
