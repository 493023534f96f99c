"""train.py trains, checkpoints, resumes the same run, and its checkpoints reload for deployment. The commands run in
this process (tests.helpers.run_command: their main with the command line); the tutorials, the newcomer's test and
the installed wheel's run them as a user's shell does."""

import subprocess
from pathlib import Path

import pytest
import torch

from kpflow.policies.neural_field import NeuralVectorField
from kpflow.utils.checkpoint import load_checkpoint
from tests.helpers import run_command


def train(tmp: Path, *extra: str) -> subprocess.CompletedProcess:
    cmd = [
        "experiment=frames_field",
        "logger=csv",
        "run_name=test",
        f"hydra.run.dir={tmp}",
        "data.n_points=60",
        "trainer.enable_progress_bar=false",
        *extra,
    ]
    done = run_command("kpflow.cli.train", *cmd)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


@pytest.mark.slow
def test_train_resume_and_reload(tmp_path):
    train(tmp_path, "trainer.max_epochs=2")
    first = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)
    assert first["epoch"] == 1 and (tmp_path / "config.yaml").exists()

    train(tmp_path, "trainer.max_epochs=4", "resume=true")
    resumed = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)
    assert resumed["epoch"] == 3 and resumed["global_step"] == 2 * first["global_step"]  # continued, not restarted

    model = load_checkpoint(NeuralVectorField, tmp_path / "checkpoints" / "last.ckpt")
    x = torch.zeros(5, 2)
    assert model(x).shape == (5, 2)
    again = load_checkpoint(NeuralVectorField, tmp_path / "checkpoints" / "last.ckpt")
    torch.testing.assert_close(model(x), again(x))
    assert not torch.allclose(model.x_std, torch.ones(2))  # standardisation travelled in the checkpoint


@pytest.mark.slow
def test_resume_without_checkpoint_is_a_clear_error(tmp_path):
    done = run_command(
        "kpflow.cli.train", "experiment=frames_field", "logger=none", f"hydra.run.dir={tmp_path}", "resume=true"
    )
    assert done.returncode != 0 and "does not exist" in done.stderr


def test_corrupt_checkpoint_is_a_clear_error(tmp_path):
    bad = tmp_path / "broken.ckpt"
    bad.write_bytes(b"not a checkpoint at all")
    with pytest.raises(ValueError, match="is not a readable checkpoint"):
        load_checkpoint(NeuralVectorField, bad)
    with pytest.raises(FileNotFoundError):
        load_checkpoint(NeuralVectorField, tmp_path / "missing.ckpt")


def test_bad_data_config_is_a_clear_error():
    from kpflow.maps import ILWRMap
    from kpflow.tasks.frames.transported_demos import TransportedDemosDataModule

    with pytest.raises(ValueError, match="target must index"):
        TransportedDemosDataModule(ILWRMap, n_configs=4, target=7)


def train_then_resume(train: list[str], run: Path) -> Path:
    """Run ``kpflow-train *train`` for one epoch, then resume it to two; the resumed run continues the step count.
    Returns the run's last.ckpt."""
    done = run_command("kpflow.cli.train", *train, "trainer.max_epochs=1")
    assert done.returncode == 0, done.stderr[-3000:]
    last = run / "checkpoints" / "last.ckpt"
    first_step = torch.load(last, map_location="cpu", weights_only=True)["global_step"]
    done = run_command("kpflow.cli.train", *train, "trainer.max_epochs=2", "resume=true")
    assert done.returncode == 0, done.stderr[-3000:]
    assert torch.load(last, map_location="cpu", weights_only=True)["global_step"] == 2 * first_step  # continued
    return last


@pytest.mark.slow
def test_kcfm_trains_resumes_loads_and_evaluates_from_the_cli(tmp_path):
    import json

    import numpy as np

    import kpflow
    from kpflow.tasks.pusht import PushTEnv, split_config

    demos = f"data.path={tmp_path / 'demos.zarr'}"
    train = ["experiment=pusht_kcfm", "data.n_episodes=2", "data.workers=1", demos,
             "data.batch_size=64", "logger=csv", f"hydra.run.dir={tmp_path / 'run'}"]  # fmt: skip
    last = train_then_resume(train, tmp_path / "run")
    from kpflow.policies.config import PolicyConfig
    from kpflow.tasks.pusht.task import PushTTask
    from kpflow.utils.checkpoint import read_checkpoint

    assert PolicyConfig.of_checkpoint(read_checkpoint(last)).layout == PushTTask.policy_layout.record()  # task=pusht

    policy = kpflow.load_policy(last, steps=4, execute=8)
    obs, _ = PushTEnv().reset(options={"config": split_config("in_distribution", 0)})
    policy.reset(0)
    a = policy.act(obs)
    policy.reset(0)
    assert a.shape == (8, 2) and np.isfinite(a).all() and np.array_equal(a, policy.act(obs))

    evaluate = ["policy=kcfm", f"policy.checkpoint={last}", "policy.steps=2", "split=in_distribution",
                "n_configs=1", "workers=1", "experiment.trial.max_steps=16", "experiment.videos=0", "logger=none", f"hydra.run.dir={tmp_path / 'eval'}"]  # fmt: skip
    done = run_command("kpflow.cli.evaluate", *evaluate)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads((tmp_path / "eval" / "results.json").read_text())["summary"][0]["episodes"] == 1


@pytest.mark.slow
def test_learned_map_trains_resumes_and_transports_from_the_cli(tmp_path):
    """train.py experiment=pusht_map (on a store collected for the run), resumed; then evaluate.py policy=transport
    map=learned with its checkpoint."""
    import json

    demos = f"data.sampler.path={tmp_path / 'demos.zarr'}"
    train = ["experiment=pusht_map", "data.sampler.n_episodes=2", "data.sampler.workers=1", demos,
             "data.n_pairs=96", "data.batch_size=32", "model.n_layers=4", "logger=csv", f"hydra.run.dir={tmp_path / 'run'}"]  # fmt: skip
    last = train_then_resume(train, tmp_path / "run")
    assert (tmp_path / "run" / "config.yaml").exists()

    evaluate = ["policy=transport", "map=learned", f"map.checkpoint={last}", "policy.fit_on=all",
                "data.goals=recorded", "data.n_episodes=2",
                f"data.path={tmp_path / 'demos.zarr'}", "split=in_distribution", "n_configs=1", "workers=1",
                "experiment.trial.max_steps=16", "experiment.videos=0", "logger=none", f"hydra.run.dir={tmp_path / 'eval'}"]  # fmt: skip
    done = run_command("kpflow.cli.evaluate", *evaluate)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads((tmp_path / "eval" / "results.json").read_text())["summary"][0]["episodes"] == 1
