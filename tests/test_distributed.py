"""Training past one process with Lightning's own engines: DDP on the CPU (2 processes over gloo, kpflow/conf/trainer/ddp_cpu.yaml)
trains exactly like one process where it should (a deterministic loss on whole-dataset batches: each process's
half-batch mean gradient, averaged, is the full batch's), and Hydra's submitit launcher runs a train.py sweep as
local jobs (kpflow/conf/hydra/launcher/local.yaml; slurm.yaml is its cluster twin)."""

import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
BASE = [
    "experiment=frames_field",
    "logger=csv",
    "data.n_points=60",
    "trainer.enable_progress_bar=false",
    "trainer.max_epochs=3",
    "data.batch_size=4096",
]


def train(*args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    done = subprocess.run(
        [sys.executable, "train.py", *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done


@pytest.mark.slow
def test_ddp_on_cpu_trains_like_one_process(tmp_path):
    train(*BASE, "run_name=one", f"hydra.run.dir={tmp_path / 'one'}")
    train(*BASE, "run_name=two", f"hydra.run.dir={tmp_path / 'two'}", "trainer=ddp_cpu")
    one = torch.load(tmp_path / "one" / "checkpoints" / "last.ckpt", weights_only=True)
    two = torch.load(tmp_path / "two" / "checkpoints" / "last.ckpt", weights_only=True)
    assert (tmp_path / "two" / "train_ddp_process_1.log").exists()  # a second process really trained
    assert yaml.safe_load((tmp_path / "two" / "config.yaml").read_text())["trainer"]["devices"] == 2
    assert one["global_step"] == two["global_step"] == 3
    for name, weight in one["state_dict"].items():
        torch.testing.assert_close(two["state_dict"][name], weight, rtol=0, atol=1e-5)  # float32 sums in another order


@pytest.mark.slow
def test_submitit_local_launcher_runs_a_train_sweep(tmp_path):
    train(
        "-m",
        "hydra/launcher=local",
        *BASE,
        "trainer.max_epochs=1",
        "seed=0,1",
        f"hydra.sweep.dir={tmp_path}",
        timeout=600,
    )
    for job in (0, 1):
        assert (tmp_path / str(job) / "checkpoints" / "last.ckpt").exists()
        assert yaml.safe_load((tmp_path / str(job) / "config.yaml").read_text())["seed"] == job
    assert list((tmp_path / ".submitit").glob("*/*_log.out"))  # the jobs ran through submitit
