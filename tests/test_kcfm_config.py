"""The K-CFM in LeRobot's shape (issue 65): one config of groups, the network and the objective each a registered name
plus options, a processor fitted from what the data module passes in, older flat checkpoints migrated on read."""

import inspect
from pathlib import Path

import lightning
import numpy as np
import pytest
import torch
from torch import nn

from kpflow.data.chunks import ChunkDataModule
from kpflow.policies.kcfm import KCFM
from kpflow.policies.kcfm.config import KCFMConfig, migrate
from kpflow.policies.kcfm.networks import NETWORKS, build_network
from kpflow.tasks.pusht.geometry import N_KEYPOINTS
from kpflow.utils.checkpoint import load_checkpoint
from tests.helpers import walk_to_block_store

ROOT = Path(__file__).resolve().parents[1]
SMALL = {"name": "unet", "down_dims": [16, 32], "time_dim": 16}


def test_the_constructor_takes_one_argument_per_group():
    assert len(inspect.signature(KCFM.__init__).parameters) - 1 <= 12
    model = KCFM(
        N_KEYPOINTS,
        horizon=8,
        network=SMALL,
        objective="ddpm",
        sampler={"steps": 4},
        optim={"lr": 3e-4, "lr_schedule": "constant"},
    )
    assert model.config == KCFMConfig.of(**model.hparams)  # the hyper-parameters are the config, plain
    assert model.hparams.objective == {"name": "ddpm"} and model.hparams.sampler == {"steps": 4, "solver": None}
    assert model.sampler() == (4, "ddim") and model.configure_optimizers().defaults["lr"] == 3e-4
    with pytest.raises(ValueError, match="bad optim options"):
        KCFM(N_KEYPOINTS, optim={"learning_rate": 1e-3})
    with pytest.raises(ValueError, match="optim.lr_schedule must be one of"):
        KCFM(N_KEYPOINTS, optim={"lr_schedule": "step"})
    with pytest.raises(ValueError, match="bad options .* for network 'transformer'.*down_dims"):
        KCFM(N_KEYPOINTS, network={"name": "transformer", "down_dims": [16, 32]})


def test_a_new_network_is_a_builder_and_a_registry_entry(monkeypatch):
    class Linear(nn.Module):
        """The smallest denoiser: one linear map of the noisy chunk, the time and the condition."""

        def __init__(self, dims, width: int) -> None:
            super().__init__()
            self.a, self.h = dims.action_dim, dims.horizon
            self.layer = nn.Linear(self.a * self.h + 1 + dims.cond_dim, self.a * self.h)
            self.width = width

        def forward(self, x, t, c):
            t = torch.as_tensor(t, dtype=x.dtype).expand(len(x))[:, None]
            return self.layer(torch.cat([x.flatten(1), t, c], -1)).reshape(len(x), self.h, self.a)

    monkeypatch.setitem(NETWORKS, "linear", Linear)
    model = KCFM(N_KEYPOINTS, horizon=4, network={"name": "linear", "width": 3})
    assert isinstance(model.net, Linear) and model.net.width == 3
    assert model.sample(np.zeros((N_KEYPOINTS, 2)), steps=2).shape == (1, 4, 2)
    with pytest.raises(ValueError, match="unknown network 'mlp'; choose one of"):
        build_network("mlp", None)


def test_training_without_a_fitted_processor_is_refused_by_name(tmp_path):
    walk_to_block_store(tmp_path / "demos.zarr")
    data = ChunkDataModule(tmp_path / "demos.zarr", horizon=8, batch_size=64, val_fraction=0.0)
    model = KCFM(N_KEYPOINTS, horizon=8, network=SMALL)
    trainer = lightning.Trainer(max_steps=1, accelerator="cpu", logger=False, enable_checkpointing=False,
                                enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)  # fmt: skip
    with pytest.raises(
        ValueError, match=r"processor was never fitted: call model.fit_processor\(datamodule.training_chunks\(\)\)"
    ):
        trainer.fit(model, datamodule=data)
    chunks = data.training_chunks()
    keypoints, actions, mask = data.train_set.arrays()
    assert chunks.keypoints.shape == keypoints.shape and (chunks.horizon, chunks.n_obs) == (8, 1)
    model.fit_processor(chunks)
    assert model.processor.fitted and torch.allclose(model.processor.kp_mean.double(),
                                                     torch.as_tensor(keypoints.reshape(len(keypoints), -1).astype(np.float64).mean(0)))  # fmt: skip
    with pytest.raises(ValueError, match="the data's chunk horizon 8 differs from the model's horizon=4"):
        KCFM(N_KEYPOINTS, horizon=4, network=SMALL).fit_processor(chunks)


def _flat(model: KCFM) -> dict:
    """The model's hyper-parameters as a checkpoint from before the config wrote them: one flat list of arguments."""
    hp = model.config
    return {"n_keypoints": hp.n_keypoints, "horizon": hp.horizon, "n_obs": hp.n_obs, "action_dim": hp.action_dim,
            "keypoint_dim": hp.keypoint_dim, **{k: v for k, v in vars(hp.processor).items()},
            "objective": hp.objective.name, "objective_options": hp.objective.options, "sample_steps": hp.sampler.steps,
            "solver": hp.sampler.solver, "network": hp.network.name, **hp.network.options,
            "d_model": 128, "n_layers": 4, "n_heads": 4,  # the other network's options, which built nothing
            **vars(hp.optim)}  # fmt: skip


def test_a_checkpoint_of_the_older_flat_layout_loads_and_acts_the_same(tmp_path):
    model = KCFM(
        N_KEYPOINTS, horizon=8, network=SMALL, objective={"name": "ddpm", "train_steps": 50}, sampler={"steps": 3}
    )
    model.processor.fit(np.random.default_rng(0).normal(200, 50, (64, N_KEYPOINTS, 2)), np.zeros((64, 8, 2)) + 3.0)
    flat = _flat(model)
    assert migrate(flat) == model.hparams  # every value lands in its group; the unused network's options dropped
    old = {k.removeprefix("processor."): v for k, v in model.state_dict().items()}  # statistics at the top, as then
    torch.save({"state_dict": old, "hyper_parameters": flat}, tmp_path / "old.ckpt")
    loaded = load_checkpoint(KCFM, tmp_path / "old.ckpt")
    assert loaded.config == model.config and loaded.sampler() == (3, "ddim")
    kp = np.random.default_rng(1).normal(200, 50, (2, N_KEYPOINTS, 2))
    g = lambda: torch.Generator().manual_seed(4)  # noqa: E731
    assert torch.equal(loaded.sample(kp, generator=g()), model.eval().sample(kp, generator=g()))
    assert migrate(model.hparams) is model.hparams  # a current file is read as it is


@pytest.mark.parametrize("path", sorted((ROOT / "release").glob("*.ckpt")), ids=lambda p: p.name)
def test_every_release_loads_into_the_config(path):
    """The released files were written before the config (flat hyper-parameters, statistics at the top)."""
    model = load_checkpoint(KCFM, path)
    assert model.processor.fitted and model.config.network.name == "unet"
    assert KCFM(**model.hparams).state_dict().keys() == model.state_dict().keys()


def test_the_config_groups_compose_from_the_command_line():
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    with initialize_config_dir(str(ROOT / "kpflow" / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=pusht_kcfm", "model/network=transformer", "model.network.n_layers=2",
                                          "model/objective=ddpm", "model.objective.train_steps=50", "model.sampler.steps=4"])  # fmt: skip
        fast = compose("train", overrides=["experiment=pusht_kcfm_fast"])
    model = instantiate(cfg.model, _convert_="all")
    assert model.hparams.network == {"name": "transformer", "d_model": 128, "n_layers": 2, "n_heads": 4, "time_dim": 64}
    assert model.objective.train_steps == 50 and model.sampler() == (4, "ddim")
    assert (
        fast.model.objective.name == "reflow"
        and fast.model.sampler.steps == 2
        and fast.model.network.down_dims == [64, 128]
    )


def test_a_trained_checkpoint_records_the_tasks_layout(tmp_path):
    """kpflow-train task=... (train.record_layout): every checkpoint the run writes carries the layout, and a model of
    another size than the task's is refused before training."""
    from kpflow.cli.train import record_layout
    from kpflow.policies.config import PolicyConfig
    from kpflow.tasks.pusht.task import PushTTask
    from kpflow.utils.checkpoint import read_checkpoint

    walk_to_block_store(tmp_path / "demos.zarr")
    data = ChunkDataModule(tmp_path / "demos.zarr", horizon=8, batch_size=64, val_fraction=0.0)
    model = KCFM(N_KEYPOINTS, horizon=8, network=SMALL)
    layout = PushTTask.policy_layout
    record_layout(model, layout)
    model.fit_processor(data.training_chunks())
    trainer = lightning.Trainer(max_steps=1, accelerator="cpu", logger=False, enable_checkpointing=False,
                                enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)  # fmt: skip
    trainer.fit(model, datamodule=data)
    trainer.save_checkpoint(tmp_path / "last.ckpt")
    saved = PolicyConfig.of_checkpoint(read_checkpoint(tmp_path / "last.ckpt"))
    assert saved.kind == "kcfm" and saved.layout == layout.record()
    with pytest.raises(
        ValueError, match="the model is sized for 25 keypoints in 3-D .* the task's layout has 25 keypoints in 2-D"
    ):
        record_layout(KCFM(N_KEYPOINTS, keypoint_dim=3, action_dim=2, network=SMALL), layout)


def test_an_action_dimension_that_never_changes_comes_out_as_its_constant():
    """Issue 66: a gripper column constant in the data came out as the network's residual noise around it."""
    rng = np.random.default_rng(0)
    keypoints = rng.normal(0.0, 1.0, (64, 4, 3))
    chunks = np.concatenate([rng.normal(0.0, 0.1, (64, 8, 3)), np.full((64, 8, 1), 0.04)], -1)
    model = KCFM(4, horizon=8, keypoint_dim=3, action_dim=4, network=SMALL)  # untrained: its outputs are noise
    model.processor.fit(keypoints, chunks)
    assert model.processor.action_scale[3] == 0 and model.processor.action_scale[:3].min() > 0
    sampled = model.sample(keypoints[:5], steps=2, generator=torch.Generator().manual_seed(0))
    assert torch.all(sampled[..., 3] == torch.tensor(0.04, dtype=torch.float32))
    assert sampled[..., :3].std() > 0  # the others as sampled
    x = model.processor.normalise_actions(torch.as_tensor(chunks[:2]))
    assert torch.isfinite(x).all() and x[..., 3].abs().max() < 1e-6  # (the centre is stored in float32)
