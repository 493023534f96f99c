"""Released checkpoints: weights and config only, loadable with weights_only through kpflow.load_policy; and the
ones committed under release/ load and act on the CPU."""

from pathlib import Path

import lightning
import numpy as np
import pytest
import torch

from kpflow import load_policy
from kpflow.data.chunks import ChunkDataModule
from kpflow.policies.kcfm import KCFM
from kpflow.release import KEEP, main, release
from kpflow.tasks.pusht import PushTEnv, split_config, standard_config
from tests.helpers import walk_to_block_store

ROOT = Path(__file__).resolve().parents[1]
RELEASED = sorted((ROOT / "release").glob("*.ckpt"))


def test_release_keeps_weights_and_config_only(tmp_path):
    walk_to_block_store(tmp_path / "demos.zarr")
    lightning.seed_everything(0, verbose=False)
    model = KCFM(horizon=8, down_dims=[16, 32], time_dim=16)
    trainer = lightning.Trainer(max_steps=5, accelerator="cpu", logger=False, enable_checkpointing=False, default_root_dir=tmp_path,
                                enable_progress_bar=False, enable_model_summary=False)
    trainer.fit(model, datamodule=ChunkDataModule(tmp_path / "demos.zarr", horizon=8, batch_size=32, val_fraction=0.0))
    trainer.save_checkpoint(tmp_path / "full.ckpt")
    main([str(tmp_path / "full.ckpt"), str(tmp_path / "out" / "small.ckpt"), "--note", "tiny"])
    small = torch.load(tmp_path / "out" / "small.ckpt", weights_only=True)
    assert set(small) <= {*KEEP, "release"} and small["release"]["note"] == "tiny"
    assert "optimizer_states" in torch.load(tmp_path / "full.ckpt", weights_only=True)
    assert (tmp_path / "out" / "small.ckpt").stat().st_size < (tmp_path / "full.ckpt").stat().st_size
    obs = PushTEnv().reset(options={"config": split_config("in_distribution", 0)})[0]
    a, b = load_policy(tmp_path / "full.ckpt"), load_policy(tmp_path / "out" / "small.ckpt")
    a.reset(3), b.reset(3)
    np.testing.assert_array_equal(a.act(obs), b.act(obs))  # the same policy
    with pytest.raises(FileNotFoundError):
        release(tmp_path / "missing.ckpt", tmp_path / "x.ckpt")
    assert not (tmp_path / "x.ckpt").exists()


@pytest.mark.skipif(not RELEASED, reason="no released checkpoints under release/")
def test_released_checkpoints_load_and_act_on_cpu():
    assert sum(p.stat().st_size for p in RELEASED) <= 25e6  # 25 MB at most in all
    env = PushTEnv()
    for path in RELEASED:
        policy = load_policy(path)
        assert set(torch.load(path, weights_only=True)) <= {*KEEP, "release"}
        obs, _ = env.reset(options={"config": standard_config(100_000)})
        obs = dict(obs, keypoints_history=np.stack([obs["keypoints"]] * policy.n_obs))
        policy.reset(0)
        chunk = policy.act(obs)
        assert chunk.shape == (policy.execute, 2) and np.isfinite(chunk).all()
        assert np.abs(chunk - obs["agent_pos"]).max() < 200  # targets near the agent: it acts, not noise


STORE = ROOT / "release" / "pusht_table1_35_corrected.zarr"


@pytest.mark.skipif(not STORE.exists(), reason="no released Table 1 store under release/")
def test_released_table1_store_gives_transported_kcfm_its_sources():
    """Transported K-CFM of Table 1 is the released K-CFM plus the store it was trained on (35 demos + corrections)."""
    from kpflow.data.episode_store import EpisodeStore
    from kpflow.data.pusht_demos import pusht_datamodule
    from kpflow.policies.pusht_build import transported_kcfm

    store = EpisodeStore(STORE)
    assert len(store) > 35 and store.n_steps > 6000
    policy = transported_kcfm(str(ROOT / "release" / "pusht_table1_kcfm_35_corrected.ckpt"), pusht_datamodule(str(STORE), n_episodes=None))
    obs, _ = PushTEnv("object_ood").reset(options={"config": split_config("object_ood", 10_000)})
    policy.reset(0)
    chunk = policy.act(obs)
    assert chunk.shape == (8, 2) and np.isfinite(chunk).all()
    assert (chunk >= 0).all() and (chunk <= 1024).all()  # in the arena
    # A smooth path: steps at most twice the store's largest demonstrated step per axis (the map may stretch a
    # chunk), and consecutive steps that change by less than one such step.
    actions, ends = store.field("action"), store.episode_ends
    within = np.setdiff1d(np.arange(1, len(actions)), ends[:-1])  # rows whose previous row is in the same episode
    demo_step = np.abs(actions[within] - actions[within - 1]).max()
    steps = np.diff(chunk, axis=0)
    assert np.abs(steps).max() < 2 * demo_step and np.abs(np.diff(steps, axis=0)).max() < demo_step
