"""Every objective and network trains, saves, reloads from a weights-only checkpoint and acts; the observation
history reaches the model through the dataset, the policy and the rollout."""

import lightning
import numpy as np
import pytest
import torch

from kpflow.data.chunks import ChunkDataModule
from kpflow.policies.kcfm.model import KCFM
from kpflow.policies.kcfm.policy import KCFMPolicy
from kpflow.tasks.pusht import PushTEnv, split_config
from kpflow.tasks.pusht.geometry import N_KEYPOINTS, goal_frame
from kpflow.tasks.pusht.rollout import run_episode
from kpflow.utils.checkpoint import load_checkpoint, read_checkpoint
from tests.helpers import walk_to_block_store

H = 8


@pytest.fixture(scope="module")
def store_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("variants") / "demos.zarr"
    walk_to_block_store(path)
    return path


VARIANTS = [
    ("icfm", "unet", 1),
    ("otcfm", "unet", 1),
    ("ddpm", "unet", 2),
    ("icfm", "transformer", 2),
    ("ddpm", "transformer", 1),
]


@pytest.mark.parametrize(("objective", "network", "n_obs"), VARIANTS)
def test_train_save_reload_act(tmp_path, store_path, objective, network, n_obs):
    lightning.seed_everything(0, verbose=False)
    small = {
        "unet": dict(down_dims=[16, 32], time_dim=16),
        "transformer": dict(d_model=32, n_layers=2, n_heads=2, time_dim=16),
    }
    model = KCFM(
        N_KEYPOINTS,
        horizon=H,
        n_obs=n_obs,
        objective=objective,
        network={"name": network, **small[network]},
        optim={"lr": 3e-3},
        processor={"goal_frame": goal_frame()},
    )
    datamodule = ChunkDataModule(store_path, horizon=H, batch_size=64, n_obs=n_obs, val_fraction=0.0)
    trainer = lightning.Trainer(
        max_steps=40,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        default_root_dir=tmp_path,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    model.fit_processor(datamodule.training_chunks())
    trainer.fit(model, datamodule=datamodule)
    items = [datamodule.train_set[i] for i in range(0, len(datamodule.train_set), 3)]
    batch = {k: torch.stack([it[k] for it in items]) for k in ("history", "actions", "mask")}
    fresh = KCFM(**model.hparams)
    fresh.load_state_dict(
        {k: v for k, v in model.state_dict().items() if not k.startswith(("net.", "ema_net."))}, strict=False
    )
    with torch.no_grad():
        g = lambda: torch.Generator().manual_seed(1)  # noqa: E731
        assert model.loss(batch, generator=g()).item() < 0.7 * fresh.loss(batch, generator=g()).item()  # it learned

    ckpt = tmp_path / "model.ckpt"
    trainer.save_checkpoint(ckpt)
    hparams = read_checkpoint(ckpt)["hyper_parameters"]  # weights_only: plain names and numbers
    assert (hparams["objective"]["name"], hparams["network"]["name"], hparams["n_obs"]) == (objective, network, n_obs)
    loaded = load_checkpoint(KCFM, ckpt)
    history = batch["history"][:3]
    a = loaded.sample(history, steps=4, generator=torch.Generator().manual_seed(7))
    b = model.eval().sample(history, steps=4, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a, b) and a.shape == (3, H, 2) and torch.isfinite(a).all()

    # the policy acts in a real Push-T episode; the rollout hands it the history it needs
    policy = KCFMPolicy(loaded, steps=4, execute=4)
    assert policy.n_obs == n_obs
    seen = []
    act = policy.act
    policy.act = lambda obs: seen.append(obs) or act(obs)
    result = run_episode(PushTEnv(), policy, split_config("in_distribution", 0, 0), max_steps=12, seed=0)
    assert result.steps == 12 and len(seen) == 3
    if n_obs > 1:
        assert seen[0]["keypoints_history"].shape == (n_obs, 25, 2)
        np.testing.assert_array_equal(seen[0]["keypoints_history"][0], seen[0]["keypoints"])  # padded at the start
        assert not np.array_equal(seen[1]["keypoints_history"][-2], seen[1]["keypoints"])  # then consecutive steps
        with pytest.raises(ValueError, match="keypoints_history"):
            act({"keypoints": seen[0]["keypoints"]})
    else:
        assert "keypoints_history" not in seen[0]


def test_history_length_must_match_the_data():
    model = KCFM(N_KEYPOINTS, horizon=H, n_obs=2)
    with pytest.raises(ValueError, match="needs 'history'"):
        model.loss(
            {"obs": torch.zeros(2, 25, 2), "actions": torch.zeros(2, H, 2), "mask": torch.ones(2, H, dtype=torch.bool)}
        )
    with pytest.raises(ValueError, match="keypoints must have shape"):
        model.sample(np.zeros((25, 2)))  # one frame where two are needed
    with pytest.raises(ValueError, match="unknown network 'mlp'"):
        KCFM(N_KEYPOINTS, network="mlp")
    with pytest.raises(ValueError, match="unknown objective"):
        KCFM(N_KEYPOINTS, objective="score")


@pytest.mark.parametrize("experiment", ["pusht_kcfm", "pusht_kcfm_gpu"])
def test_training_experiments_compose_into_a_matching_model(experiment):
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from tests.test_release import ROOT

    with initialize_config_dir(str(ROOT / "kpflow" / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=[f"experiment={experiment}", "logger=none"])
    model = instantiate(cfg.model, _convert_="all")
    assert model.hparams.horizon == cfg.data.horizon and model.hparams.n_obs == cfg.data.n_obs
    assert isinstance(model.hparams.network["down_dims"], list)  # plain hparams: the checkpoint loads with weights_only
    # the task's experiment gives the layout and the goal frame (kpflow/conf/model/kcfm.yaml has neither)
    assert model.hparams.n_keypoints == N_KEYPOINTS and model.hparams.processor["goal_frame"] == goal_frame()
    if experiment == "pusht_kcfm_gpu":
        assert (
            cfg.trainer.accelerator == "gpu"
            and model.hparams.network["down_dims"] == [256, 512, 1024]
            and model.hparams.n_obs == 2
        )
