"""Few-step K-CFM policies end to end on a tiny synthetic episode store: MeanFlow trained from scratch and reflow
distilled from a trained teacher each train, save and reload (the student without its teacher's file), and sample
in one network call better than an untrained network / the teacher's own one-step samples; a checkpoint's sampling
settings are the policy's defaults."""

import lightning
import pytest
import torch

from kpflow.data.chunks import ChunkDataModule
from kpflow.policies.kcfm.model import KCFM
from kpflow.policies.kcfm.policy import KCFMPolicy
from kpflow.tasks.pusht.geometry import N_KEYPOINTS
from kpflow.utils.checkpoint import load_checkpoint

H = 8
SMALL = dict(horizon=H, network={"name": "unet", "down_dims": (16, 32), "time_dim": 16}, optim={"lr": 3e-3})


def _fit(model: KCFM, store, tmp_path, steps: int, name: str):
    lightning.seed_everything(0, verbose=False)
    trainer = lightning.Trainer(max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False, default_root_dir=tmp_path,
                                enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0, limit_val_batches=0)  # fmt: skip
    datamodule = ChunkDataModule(store, horizon=H, batch_size=64)
    model.fit_processor(datamodule.training_chunks())
    trainer.fit(model, datamodule=datamodule)
    path = tmp_path / f"{name}.ckpt"
    trainer.save_checkpoint(path)
    items = [datamodule.train_set[i] for i in range(0, len(datamodule.train_set), 3)]
    return path, {k: torch.stack([it[k] for it in items]) for k in ("obs", "actions", "mask")}


def _error(model: KCFM, batch, steps: int, solver=None) -> float:
    pred = model.eval().sample(batch["obs"], steps, torch.Generator().manual_seed(0), solver)
    return float((pred - batch["actions"]).norm(dim=-1)[batch["mask"]].median())


def test_meanflow_trains_from_scratch_saves_reloads_and_acts_in_one_call(walk_store, tmp_path):
    model = KCFM(N_KEYPOINTS, objective="meanflow", sampler={"steps": 1}, **SMALL)
    path, batch = _fit(model, walk_store, tmp_path, 150, "meanflow")
    fresh = KCFM(**model.hparams)
    fresh.load_state_dict(
        {k: v for k, v in model.state_dict().items() if not k.startswith(("net.", "ema_net."))}, strict=False
    )
    one_step, untrained = _error(model, batch, 1), _error(fresh, batch, 1)
    assert one_step < 0.45 * untrained, (one_step, untrained)  # measured: 86 px against 258 px untrained
    loaded = load_checkpoint(KCFM, path)
    assert loaded.sampler() == (1, "euler") and loaded.net.n_times == 2
    g = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    assert torch.equal(loaded.sample(batch["obs"][:4], generator=g()), model.sample(batch["obs"][:4], 1, g()))


def test_reflow_distils_a_teacher_into_one_call_and_reloads_without_it(walk_store, tmp_path):
    teacher = KCFM(N_KEYPOINTS, **SMALL)
    teacher_path, batch = _fit(teacher, walk_store, tmp_path, 200, "teacher")
    student = KCFM(N_KEYPOINTS, objective={"name": "reflow", "teacher": str(teacher_path), "teacher_steps": 8, "t_grid": 1},
                   sampler={"steps": 1}, **SMALL)  # fmt: skip
    path, _ = _fit(student, walk_store, tmp_path, 100, "student")
    # the student took the teacher's normalisation; its one call lands nearer the teacher's 8-call chunks than the
    # teacher's own single call does
    for name in ("kp_mean", "kp_std", "action_center", "action_scale"):
        assert torch.equal(getattr(student.processor, name), getattr(teacher.processor, name))
    g = lambda: torch.Generator().manual_seed(5)  # noqa: E731
    reference = teacher.eval().sample(batch["obs"], 8, g(), "midpoint")
    gap = lambda chunks: float((chunks - reference).norm(dim=-1)[batch["mask"]].median())  # noqa: E731
    distilled, undistilled = gap(student.eval().sample(batch["obs"], 1, g())), gap(teacher.sample(batch["obs"], 1, g()))
    assert distilled < 0.7 * undistilled, (distilled, undistilled)
    teacher_path.unlink()  # a trained student never reads its teacher again
    loaded = load_checkpoint(KCFM, path)
    assert loaded.sampler() == (1, "euler")
    assert torch.equal(loaded.sample(batch["obs"][:4], generator=g()), student.sample(batch["obs"][:4], generator=g()))


def test_a_teacher_of_another_layout_is_refused(tmp_path):
    teacher = KCFM(N_KEYPOINTS, **{**SMALL, "horizon": 4})
    path = tmp_path / "teacher.ckpt"
    torch.save({"state_dict": teacher.state_dict(), "hyper_parameters": dict(teacher.hparams)}, path)
    student = KCFM(N_KEYPOINTS, objective={"name": "reflow", "teacher": str(path)}, **SMALL)
    with pytest.raises(ValueError, match=r"differs from this K-CFM in \['horizon'\]: horizon 4 against 8"):
        student.attach_teacher()


def test_the_checkpoints_sampling_settings_are_the_policys_defaults():
    model = KCFM(
        N_KEYPOINTS,
        horizon=H,
        network={"name": "unet", "down_dims": (16, 32), "time_dim": 16},
        sampler={"steps": 3, "solver": "heun"},
    )
    policy = KCFMPolicy(model)
    assert (policy.steps, policy.solver) == (3, "heun")
    assert (
        KCFMPolicy(model, steps=4, solver="midpoint").steps,
        KCFMPolicy(model, steps=4, solver="midpoint").solver,
    ) == (4, "midpoint")
    assert KCFM(N_KEYPOINTS, horizon=H, objective="ddpm").sampler() == (10, "ddim")  # the objective's first solver
    with pytest.raises(ValueError, match=r"solver must be one of \('ddim',\)"):
        KCFM(N_KEYPOINTS, horizon=H, objective="ddpm", sampler={"solver": "midpoint"})
    with pytest.raises(ValueError, match="steps must be an integer in 1..100"):
        KCFMPolicy(model, steps=0)
