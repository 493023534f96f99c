"""Draw docs/guides/pusht.md's Push-T figures: the three splits with their 25 keypoints, and an expert episode as a strip.

Run: ``python docs/make_pusht_figures.py`` (writes docs/img/pusht_splits.png and docs/img/pusht_expert.png).
"""

from pathlib import Path

import numpy as np
from PIL import Image

from kpflow.tasks.pusht import SPLITS, PushTEnv, split_config
from kpflow.tasks.pusht.demonstrator import PushTExpert
from kpflow.tasks.pusht.rollout import run_episode
from kpflow.utils.io import atomic_path

OUT = Path(__file__).resolve().parent / "img"


def save(img: np.ndarray, name: str) -> None:
    with atomic_path(OUT / name) as tmp:
        Image.fromarray(img).save(tmp, format="PNG")


def main() -> None:
    tiles = []
    for split in SPLITS:
        env = PushTEnv(split=split, render_size=320, render_keypoints=True)
        env.reset(options={"config": split_config(split, 0)})
        tiles.append(env.render())
    save(np.concatenate(tiles, axis=1), "pusht_splits.png")

    config = split_config("in_distribution", 4)
    result = run_episode(PushTEnv(render_size=200), PushTExpert(), config, 600, seed=4, render=True)
    frames = [result.frames[i] for i in np.linspace(0, len(result.frames) - 1, 6).astype(int)]
    save(np.concatenate(frames, axis=1), "pusht_expert.png")
    print(f"expert: {result.steps} steps, coverage {result.coverage:.3f}; wrote {OUT}/pusht_*.png")


if __name__ == "__main__":
    main()
