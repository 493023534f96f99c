"""No entry point runs code from a checkpoint: a real checkpoint with one planted pickled object whose
``__reduce__`` calls ``os.system`` is refused by ``kpflow.load_policy``, ``load_checkpoint``, ``evaluate.py`` (both
K-CFM policies), ``train.py ... resume=true`` and a Trainer resuming through :class:`SafeCheckpointIO`; and the
planted command never runs. Non-finite weights are refused at load, naming the file and the tensor, and so are
hyper-parameters that do not build the weights' shapes (a tiny file asking for a 1.9 GB network), before anything
is allocated."""

import os
import subprocess
import sys
from pathlib import Path

import lightning
import pytest
import torch

import kpflow
from kpflow.data.chunks import ChunkDataModule
from kpflow.policies.kcfm.model import KCFM
from kpflow.tasks.pusht.geometry import N_KEYPOINTS
from kpflow.utils.checkpoint import SafeCheckpointIO, UnsafeCheckpointError, load_checkpoint, read_checkpoint
from tests.helpers import run_command, walk_to_block_store

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
    model, data = KCFM(N_KEYPOINTS, horizon=H), ChunkDataModule(tmp / "demos.zarr", horizon=H, batch_size=64)
    model.fit_processor(data.training_chunks())
    t.fit(model, datamodule=data)
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
        t.fit(
            KCFM(N_KEYPOINTS, horizon=H),
            datamodule=ChunkDataModule(kcfm_run / "demos.zarr", horizon=H, batch_size=64),
            ckpt_path=evil,
        )
    assert not marker.exists()
    torch.load(evil, weights_only=False)  # control: the payload is live, an unsafe load does run it
    assert marker.exists()


@pytest.mark.parametrize("policy", ["kcfm", "transported_kcfm"])
def test_planted_payload_is_refused_by_evaluate(kcfm_run, tmp_path, policy):
    marker = tmp_path / "pwned"
    evil = plant(kcfm_run / "good.ckpt", tmp_path / "evil.ckpt", marker)
    done = run_command("kpflow.cli.evaluate", f"policy={policy}", f"policy.checkpoint={evil}", f"data.path={tmp_path / 'demos.zarr'}",
                       "n_configs=1", "workers=1", "logger=none", f"hydra.run.dir={tmp_path / 'eval'}")  # fmt: skip
    assert done.returncode != 0 and "was refused" in done.stderr, done.stderr[-2000:]
    assert not marker.exists()


def test_planted_payload_is_refused_when_resuming_training(tmp_path):
    marker = tmp_path / "pwned"
    run = tmp_path / "run"
    base = [
        "kpflow.cli.train",
        "experiment=frames_field",
        "logger=none",
        f"hydra.run.dir={run}",
        "data.n_points=60",
        "trainer.enable_progress_bar=false",
    ]
    done = run_command(*base, "trainer.max_epochs=1")
    assert done.returncode == 0, done.stderr[-2000:]
    last = run / "checkpoints" / "last.ckpt"
    plant(last, last, marker)
    done = run_command(*base, "trainer.max_epochs=2", "resume=true")  # a payload that ran would run in this process
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


def test_hyper_parameters_that_ask_for_a_huge_network_are_refused_before_allocating(kcfm_run, tmp_path):
    """A real checkpoint (a few MB) with ``network.down_dims = [1024, 2048]`` written into its hyper-parameters and its small
    weights kept: building it would allocate ~460M parameters (1.9 GB, counted on the meta device). load_checkpoint
    refuses it naming the file and the first mismatching tensors, and a process that tries grows by well under 300 MB
    (its peak resident memory, read after the refusal)."""
    checkpoint = torch.load(kcfm_run / "good.ckpt", weights_only=True)
    checkpoint["hyper_parameters"]["network"]["down_dims"] = [1024, 2048]
    big = tmp_path / "big.ckpt"
    torch.save(checkpoint, big)
    with torch.device("meta"):
        would_build = sum(p.numel() for p in KCFM(**checkpoint["hyper_parameters"]).parameters())
    assert would_build > 400e6  # the case is live: without the check, 4 bytes each
    with pytest.raises(ValueError, match=rf"{big}: its hyper-parameters do not match its weights, refusing to build the KCFM: "
                                         r"'net\.down\.0\.0\.conv0\.block\.0\.weight' is \[32, 2, 5\] in the file, \[1024, 2, 5\] by the hyper-parameters"):  # fmt: skip
        kpflow.load_policy(big)
    script = (
        "import resource, sys, torch\n"
        "from kpflow.policies.kcfm import KCFM\n"
        "from kpflow.utils.checkpoint import load_checkpoint, read_checkpoint\n"
        "read_checkpoint(sys.argv[1])\n"  # the file itself read once: what the check may cost
        "before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
        "try:\n    load_checkpoint(KCFM, sys.argv[1])\nexcept ValueError as e:\n    print('refused', e)\n"
        "print('grew_kb', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script, str(big)], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0 and "refused" in done.stdout, done.stderr[-2000:]
    grew_mb = int(done.stdout.split("grew_kb ")[1]) / 1024
    assert grew_mb < 300, grew_mb  # building it would have taken about 1900 MB


def test_hyper_parameters_that_do_not_match_the_weights_name_the_tensors(kcfm_run, tmp_path):
    """Missing and foreign tensors are named too; a checkpoint whose hyper-parameters fit still loads."""
    checkpoint = torch.load(kcfm_run / "good.ckpt", weights_only=True)
    checkpoint["state_dict"]["extra.weight"] = torch.ones(3)
    del checkpoint["state_dict"]["processor.kp_std"]
    odd = tmp_path / "odd.ckpt"
    torch.save(checkpoint, odd)
    with pytest.raises(
        ValueError,
        match=rf"{odd}: .*'processor.kp_std' missing from the file; 'extra.weight' in the file is not in the model",
    ):
        load_checkpoint(KCFM, odd)
    assert load_checkpoint(KCFM, kcfm_run / "good.ckpt").hparams.horizon == H
