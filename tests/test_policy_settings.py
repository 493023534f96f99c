"""A policy's own settings travel in its checkpoint (kpflow/policies/settings.py): ``kpflow-release settings.*``
writes them, every builder takes them when nothing is given, what is given wins, and a run's config.yaml records
what was used."""

import lightning
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from kpflow import load_policy
from kpflow.cli.evaluate import record_used
from kpflow.cli.release import release
from kpflow.data.chunks import ChunkDataModule
from kpflow.policies.factory import kcfm
from kpflow.policies.kcfm.model import KCFM
from kpflow.policies.kcfm.policy import KCFMPolicy
from kpflow.policies.settings import CHECKPOINT_KEY, PolicySettings, effective_settings
from kpflow.policies.subgoal import SubgoalPolicy
from kpflow.serving.deployment import load_deployment
from kpflow.tasks.pusht.geometry import N_KEYPOINTS
from kpflow.tasks.pusht.task import PushTTask
from tests.helpers import bare_kcfm, walk_to_block_store


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A K-CFM trained for 5 steps on a few walk-to-block episodes (its own sampler: 10 Euler steps)."""
    tmp = tmp_path_factory.mktemp("settings")
    walk_to_block_store(tmp / "demos.zarr")
    lightning.seed_everything(0, verbose=False)
    model = KCFM(N_KEYPOINTS, horizon=8, network={"name": "unet", "down_dims": [16, 32], "time_dim": 16})
    trainer = lightning.Trainer(max_steps=5, accelerator="cpu", logger=False, enable_checkpointing=False, default_root_dir=tmp,
                                enable_progress_bar=False, enable_model_summary=False)  # fmt: skip
    data = ChunkDataModule(tmp / "demos.zarr", horizon=8, batch_size=32, val_fraction=0.0)
    model.fit_processor(data.training_chunks())
    trainer.fit(model, datamodule=data)
    trainer.save_checkpoint(tmp / "full.ckpt")
    return tmp / "full.ckpt"


def test_settings_are_checked_and_given_values_win():
    stored = PolicySettings(steps=20, reach=60, turn_deg=60)
    assert stored.record() == {"steps": 20, "reach": 60, "turn_deg": 60}
    assert stored.given(steps=None, reach=None) == stored  # None keeps the record's value
    assert stored.given(steps=4, turn_deg=False) == PolicySettings(steps=4, reach=60)  # False: the goal as observed
    assert PolicySettings().actions == 8 and PolicySettings(execute=4).actions == 4
    with pytest.raises(ValueError, match="steps must be an integer in 1..100"):
        PolicySettings(steps=0)
    with pytest.raises(ValueError, match="reach must be a positive finite number or None"):
        stored.given(reach=0)
    with pytest.raises(ValueError, match=r"ckpt X: 'policy_settings' names unknown setting\(s\) \['stepz'\]"):
        PolicySettings.from_record({"stepz": 3}, "ckpt X")
    with pytest.raises(ValueError, match="ckpt X: 'policy_settings' must be a mapping"):
        PolicySettings.from_record("steps=3", "ckpt X")
    assert PolicySettings.from_record(None) == PolicySettings()


def test_a_release_carries_its_settings_into_every_builder(trained, tmp_path):
    with pytest.raises(
        ValueError, match="no keypoint layout names them: pass the task"
    ):  # a goal limit needs the task's groups
        release(trained, tmp_path / "r.ckpt", settings={"reach": 50})
    assert not (tmp_path / "r.ckpt").exists()
    settings = {"steps": 3, "solver": "midpoint", "execute": 4, "reach": 50, "turn_deg": 40}
    dst = release(trained, tmp_path / "r.ckpt", settings=settings, layout=PushTTask.policy_layout)
    assert torch.load(dst, weights_only=True)[CHECKPOINT_KEY] == {
        "steps": 3,
        "solver": "midpoint",
        "execute": 4,
        "reach": 50,
        "turn_deg": 40,
    }
    task = PushTTask()
    policy = kcfm(str(dst), task)  # evaluate's policy=kcfm with no overrides
    assert isinstance(policy, SubgoalPolicy) and (policy.reach, policy.turn_deg) == (50.0, 40.0)
    assert (policy.policy.steps, policy.policy.solver, policy.policy.execute) == (3, "midpoint", 4)
    assert effective_settings(policy) == {
        "steps": 3,
        "solver": "midpoint",
        "execute": 4,
        "reach": 50.0,
        "turn_deg": 40.0,
    }
    given = kcfm(str(dst), task, steps=5, execute=2, reach=False)  # what is given wins; False drops the reach
    assert (given.reach, given.turn_deg, given.policy.steps, given.policy.execute) == (None, 40.0, 5, 2)
    assert isinstance(kcfm(str(dst), task, reach=False, turn_deg=False), KCFMPolicy)
    loaded = load_policy(dst)  # the whole record, with no task given: the layout travels in the file
    assert isinstance(loaded, SubgoalPolicy) and (loaded.reach, loaded.turn_deg) == (50.0, 40.0)
    assert (loaded.policy.steps, loaded.policy.solver, loaded.policy.execute) == (3, "midpoint", 4)
    served = load_deployment(dst, task)
    assert served.metadata.policy == "kcfm/reach=50/turn_deg=40" and served.metadata.action_shape == [4, 2]
    plain = bare_kcfm(trained)  # no record: the model's own sampler.steps and 8 actions
    assert (plain.steps, plain.solver, plain.execute) == (10, "euler", 8)

    again = release(dst, tmp_path / "again.ckpt", settings={"steps": 6})  # a re-release adds to the record
    record = torch.load(again, weights_only=True)
    assert record[CHECKPOINT_KEY] == {"steps": 6, "solver": "midpoint", "execute": 4, "reach": 50, "turn_deg": 40}
    assert record["release"]["source"] == str(trained)  # where the weights came from, not the file re-released

    obs = {
        "keypoints": np.asarray(
            torch.load(dst, weights_only=True)["state_dict"]["processor.kp_mean"].reshape(-1, 2), np.float64
        )
    }
    a, b = kcfm(str(dst), task), kcfm(str(again), task, steps=3)
    a.reset(1), b.reset(1)
    np.testing.assert_array_equal(a.act(obs), b.act(obs))  # the same settings act the same


def test_a_release_with_settings_that_do_not_fit_writes_nothing(trained, tmp_path):
    with pytest.raises(ValueError, match="steps must be an integer in 1..100"):
        release(trained, tmp_path / "bad.ckpt", settings={"steps": 0})
    with pytest.raises(ValueError, match="solver must be one of"):  # a flow has no DDIM: refused as it loads back
        release(trained, tmp_path / "bad.ckpt", settings={"solver": "ddim"})
    with pytest.raises(ValueError, match=r"execute = 9 is beyond the model's chunk length \(horizon 8\)"):
        release(trained, tmp_path / "bad.ckpt", settings={"execute": 9})
    assert not list(tmp_path.iterdir())


def test_a_damaged_settings_record_is_refused_naming_the_file(trained, tmp_path):
    checkpoint = torch.load(trained, weights_only=True)
    checkpoint[CHECKPOINT_KEY] = {"stepz": 3}
    torch.save(checkpoint, tmp_path / "damaged.ckpt")
    with pytest.raises(
        ValueError, match=r"damaged.ckpt is not a readable KCFM checkpoint .*unknown setting\(s\) \['stepz'\]"
    ):
        load_policy(tmp_path / "damaged.ckpt")


@pytest.mark.parametrize("record, refused", [
    ({"execute": 9}, r"execute = 9 is beyond the model's chunk length \(horizon 8\); kpflow-release settings.execute=N with N <= 8"),
    ({"execute": 0}, r"execute must be an integer >= 1"),
    ({"solver": "rk99"}, r"solver must be one of \('euler', 'midpoint', 'heun'\)"),
    ({"steps": 10**6}, r"steps must be an integer in 1..100"),
])  # fmt: skip
def test_settings_out_of_range_in_a_checkpoint_are_refused_naming_it(trained, tmp_path, record, refused):
    """Issue 63.8: a setting the model cannot act with is refused as the checkpoint loads, in one line naming it."""
    checkpoint = torch.load(trained, weights_only=True)
    checkpoint[CHECKPOINT_KEY] = record
    torch.save(checkpoint, tmp_path / "damaged.ckpt")
    with pytest.raises(ValueError, match=rf"damaged.ckpt is not a readable KCFM checkpoint .*{refused}") as refusal:
        load_policy(tmp_path / "damaged.ckpt")
    assert "\n" not in str(refusal.value)


def test_the_run_config_records_the_values_used():
    cfg = OmegaConf.create({"policy": {"steps": None, "solver": None, "execute": None, "reach": None, "turn_deg": None, "checkpoint": "x"},
                            "experiment": {"trial": {"max_steps": 1200}}})  # fmt: skip
    results = {"policy_settings": {"steps": 2, "solver": "euler", "execute": 8, "reach": 60.0},
               "max_steps": {"in_distribution": 1200, "standard": 300}, "summary": [{"condition": "standard"}]}  # fmt: skip
    record_used(cfg, results)
    assert OmegaConf.to_container(cfg.policy) == {
        "steps": 2,
        "solver": "euler",
        "execute": 8,
        "reach": 60.0,
        "turn_deg": False,
        "checkpoint": "x",
    }
    assert cfg.experiment.trial.max_steps == 300  # the standard protocol's limit, not the splits'
    mixed = {"max_steps": {"a": 1200, "b": 300}, "summary": [{"condition": "a"}, {"condition": "b"}]}
    record_used(cfg, mixed)  # conditions with different limits: the config's value stays
    assert cfg.experiment.trial.max_steps == 300
