"""No entry point runs code from a checkpoint: a real checkpoint with one planted pickled object whose
``__reduce__`` calls ``os.system`` is refused by ``kpflow.load_policy``, ``load_checkpoint``, ``evaluate.py`` (both
K-CFM policies), ``train.py ... resume=true`` and a Trainer resuming through :class:`SafeCheckpointIO`; and the
planted command never runs. Non-finite weights are refused at load, naming the file and the tensor."""

import os
import subprocess
import sys
from pathlib import Path

import lightning
import pytest
import torch

import kpflow
from kpflow.data.chunks import ChunkDataModule
from kpflow.policies.kcfm import KCFM
from kpflow.utils.checkpoint import SafeCheckpointIO, UnsafeCheckpointError, load_checkpoint, read_checkpoint
from tests.helpers import walk_to_block_store

ROOT = Path(__file__).resolve().parents[1]
H = 8


class Payload:
    """Unpickling this runs ``touch <marker>``: what a malicious checkpoint would do."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def trainer(tmp: Path, max_steps: int, **kw) -> lightning.Trainer:
    return lightning.Trainer(max_steps=max_steps, accelerator="cpu", logger=False, default_root_dir=tmp, enable_progress_bar=False,
                             enable_model_summary=False, **kw)  # fmt: skip


@pytest.fixture(scope="module")
def kcfm_run(tmp_path_factory):
    """A real K-CFM checkpoint (2 training steps on a synthetic store) and its data."""
    tmp = tmp_path_factory.mktemp("kcfm")
    walk_to_block_store(tmp / "demos.zarr")
    lightning.seed_everything(0, verbose=False)
    t = trainer(tmp, 2)
    t.fit(KCFM(horizon=H), datamodule=ChunkDataModule(tmp / "demos.zarr", horizon=H, batch_size=64))
    t.save_checkpoint(tmp / "good.ckpt")
    return tmp


def plant(src: Path, dest: Path, marker: Path) -> Path:
    checkpoint = torch.load(src, weights_only=False)  # the test's own file: trusted
    checkpoint["callbacks"]["extra"] = Payload(marker)
    torch.save(checkpoint, dest)
    return dest


def test_real_checkpoints_load_with_weights_only(kcfm_run):
    torch.load(kcfm_run / "good.ckpt", weights_only=True)  # nothing in a kpflow checkpoint needs more
    policy = kpflow.load_policy(kcfm_run / "good.ckpt", steps=2, execute=4)
    assert policy.model.hparams.horizon == H


def test_planted_payload_is_refused_in_process(kcfm_run, tmp_path):
    marker = tmp_path / "pwned"
    evil = plant(kcfm_run / "good.ckpt", tmp_path / "evil.ckpt", marker)
    for load in (lambda: kpflow.load_policy(evil), lambda: load_checkpoint(KCFM, evil), lambda: read_checkpoint(evil)):
        with pytest.raises(UnsafeCheckpointError, match=f"{evil} was refused: it holds pickled objects .*system"):
            load()
    t = trainer(tmp_path, 4, plugins=[SafeCheckpointIO()])
    with pytest.raises(UnsafeCheckpointError, match="was refused"):
        t.fit(KCFM(horizon=H), datamodule=ChunkDataModule(kcfm_run / "demos.zarr", horizon=H, batch_size=64), ckpt_path=evil)
    assert not marker.exists()
    torch.load(evil, weights_only=False)  # control: the payload is live, an unsafe load does run it
    assert marker.exists()


@pytest.mark.slow
@pytest.mark.parametrize("policy", ["kcfm", "transported_kcfm"])
def test_planted_payload_is_refused_by_evaluate(kcfm_run, tmp_path, policy):
    marker = tmp_path / "pwned"
    evil = plant(kcfm_run / "good.ckpt", tmp_path / "evil.ckpt", marker)
    cmd = [sys.executable, "evaluate.py", f"policy={policy}", f"policy.checkpoint={evil}", f"data.path={tmp_path / 'demos.zarr'}",
           "n_configs=1", "workers=1", "logger=none", f"hydra.run.dir={tmp_path / 'eval'}"]  # fmt: skip
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0 and "was refused" in done.stderr, done.stderr[-2000:]
    assert not marker.exists()


@pytest.mark.slow
def test_planted_payload_is_refused_when_resuming_training(tmp_path):
    marker = tmp_path / "pwned"
    run = tmp_path / "run"
    base = [sys.executable, "train.py", "logger=none", f"hydra.run.dir={run}", "data.n_points=60", "trainer.enable_progress_bar=false"]
    done = subprocess.run(base + ["trainer.max_epochs=1"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    last = run / "checkpoints" / "last.ckpt"
    plant(last, last, marker)
    done = subprocess.run(base + ["trainer.max_epochs=2", "resume=true"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0 and "was refused" in done.stderr, done.stderr[-2000:]
    assert not marker.exists()


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_weights_are_refused_naming_file_and_tensor(kcfm_run, tmp_path, value):
    checkpoint = torch.load(kcfm_run / "good.ckpt", weights_only=True)
    name = next(k for k in checkpoint["state_dict"] if k.startswith("ema_net.") and k.endswith("weight"))
    checkpoint["state_dict"][name].view(-1)[3] = value
    bad = tmp_path / "bad.ckpt"
    torch.save(checkpoint, bad)
    with pytest.raises(ValueError, match=rf"{bad}: weight '{name}' holds 1 NaN or inf value\(s\)"):
        kpflow.load_policy(bad)


def test_foreign_and_truncated_files_are_clear_errors(kcfm_run, tmp_path):
    truncated = tmp_path / "cut.ckpt"
    truncated.write_bytes((kcfm_run / "good.ckpt").read_bytes()[:5000])
    with pytest.raises(ValueError, match="is not a readable checkpoint"):
        kpflow.load_policy(truncated)
    plain = tmp_path / "plain.ckpt"
    torch.save({"weights": torch.ones(2)}, plain)
    with pytest.raises(ValueError, match="not a Lightning checkpoint: no state_dict"):
        kpflow.load_policy(plain)
