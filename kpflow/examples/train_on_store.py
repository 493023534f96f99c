"""Train a K-CFM on an episode store from Python (what ``kpflow-train experiment=kcfm`` does from configs):
``python -m kpflow.examples.train_on_store [STORE] [--epochs 5]``.

Without a store it writes a small one first (a point walking to a target: keypoints ``[5, 2]``, actions ``[2]``).
It builds the datamodule, reads the model's size from the data, trains with Lightning, saves the checkpoint and acts
with the policy loaded back the way deployment loads it.
"""

import argparse
from pathlib import Path

import lightning
import numpy as np

import kpflow
from kpflow.data.chunks import ChunkDataModule
from kpflow.data.episode_store import EpisodeStore
from kpflow.policies.kcfm.model import KCFM


def walking_store(path: Path, episodes: int = 40) -> Path:
    rng = np.random.default_rng(0)
    corners = 0.05 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    with EpisodeStore(path, mode="a") as store:
        for _ in range(episodes):
            target, agent = rng.uniform(0.3, 0.7, 2), rng.uniform(0, 1, 2)
            keypoints, actions = [], []
            for _ in range(25):
                keypoints.append(np.vstack([target + corners, agent]))
                agent = agent + 0.2 * (target - agent)
                actions.append(agent)
            store.add_episode({"keypoints": np.array(keypoints, np.float32), "action": np.array(actions, np.float32)})
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "store", nargs="?", help="an episode store or LeRobot dataset (default: a small one written here)"
    )
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--out", default="train_on_store")
    args = parser.parse_args()
    out = Path(args.out)
    store = Path(args.store) if args.store else walking_store(out / "demos.zarr")

    lightning.seed_everything(0, verbose=False)
    data = ChunkDataModule(store, horizon=16, n_obs=2, batch_size=64, val_fraction=0.1)
    model = KCFM(**data.model_dims(), horizon=16, n_obs=2, network={"name": "unet", "down_dims": [32, 64]})
    model.fit_processor(data.training_chunks())  # the frames' statistics, from the training episodes
    trainer = lightning.Trainer(max_epochs=args.epochs, accelerator="auto", logger=False, enable_checkpointing=False,
                                enable_progress_bar=False, enable_model_summary=False, default_root_dir=out)  # fmt: skip
    trainer.fit(model, datamodule=data)
    trainer.save_checkpoint(out / "kcfm.ckpt")
    print(
        f"trained {args.epochs} epochs: val loss {float(trainer.callback_metrics['val/loss']):.3f}; checkpoint {out / 'kcfm.ckpt'}"
    )

    policy = kpflow.load_policy(out / "kcfm.ckpt")  # weights_only loading, as deployment does
    policy.reset(seed=0)
    history = data.val_set[0]["history"].numpy().astype(np.float64)
    chunk = policy.act({"keypoints": history[-1], "keypoints_history": history})
    print(f"first action chunk {list(chunk.shape)}: {np.round(chunk[:2], 3).tolist()} ...")


if __name__ == "__main__":
    main()
