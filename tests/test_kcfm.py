"""K-CFM: the 1-D U-Net, the flow-matching loss in closed form, goal-frame equivariance, input checks, and a real
Lightning run on a tiny synthetic episode store (train, sample, checkpoint, reload, resume)."""

import math

import lightning
import numpy as np
import pytest
import torch

from kpflow.data.chunks import ChunkDataModule
from kpflow.data.episode_store import EpisodeStore
from kpflow.policies.checks import INPUT_MARGIN
from kpflow.policies.kcfm.losses import fill_padding, masked_mse
from kpflow.policies.kcfm.model import KCFM
from kpflow.policies.kcfm.networks.unet1d import ConditionalUnet1D
from kpflow.policies.kcfm.sampling import MAX_STEPS
from kpflow.tasks.pusht.geometry import N_KEYPOINTS, observation_keypoints
from kpflow.tasks.pusht.geometry import goal_frame as pusht_goal_frame
from tests.helpers import walk_to_block_store


def pusht_kcfm(goal_frame: bool = False, relative: bool = False, **kwargs) -> KCFM:
    """A K-CFM for Push-T's 25 keypoints, in the goal T's frame or the world's (actions relative to the agent or not)."""
    processor = {"goal_frame": pusht_goal_frame() if goal_frame else None, "relative": relative}
    return KCFM(N_KEYPOINTS, processor=processor, **kwargs)


# ------------------------------------------------------------------------------------------------ U-Net


@pytest.mark.parametrize(
    ("down_dims", "horizon"), [((32, 64), 16), ((32, 64), 20), ((32, 64, 128), 20), ((32, 64, 128), 18), ((32, 64), 7)]
)
def test_unet_shape_and_conditioning(down_dims, horizon):
    torch.manual_seed(0)
    net = ConditionalUnet1D(action_dim=2, cond_dim=50, down_dims=down_dims)
    x, t, c = torch.randn(3, horizon, 2), torch.rand(3), torch.randn(3, 50)
    v = net(x, t, c)
    assert v.shape == (3, horizon, 2) and torch.isfinite(v).all()
    assert (net(x, t, c + 0.5) - v).abs().max() > 1e-3  # the condition is used
    assert (net(x, t + 0.1, c) - v).abs().max() > 1e-3  # and the flow time
    torch.testing.assert_close(net(x[:1], t[:1], c[:1]), v[:1], atol=1e-5, rtol=1e-5)  # items are independent


def test_unet_rejects_bad_shapes():
    net = ConditionalUnet1D(cond_dim=4)
    with pytest.raises(ValueError, match="x must have shape"):
        net(torch.zeros(2, 8, 3), torch.zeros(2), torch.zeros(2, 4))
    with pytest.raises(ValueError, match="condition must have shape"):
        net(torch.zeros(2, 8, 2), torch.zeros(2), torch.zeros(2, 5))
    with pytest.raises(ValueError, match="divisible by n_groups"):
        ConditionalUnet1D(down_dims=(30, 60))


# ------------------------------------------------------------------------------------- masked loss, closed form


def test_masked_mse_and_fill_padding_by_hand():
    pred = torch.zeros(2, 3, 2)
    target = torch.tensor([[[1.0, 1.0], [2.0, 0.0], [100.0, 100.0]], [[0.0, 3.0], [float("nan"), 0.0], [0.0, 0.0]]])
    mask = torch.tensor([[True, True, False], [True, False, False]])
    # real steps: (1 + 1) / 2, (4 + 0) / 2, (0 + 9) / 2 -> mean 15 / 6 = 2.5; padded steps (even NaN) do not count
    assert masked_mse(pred, target, mask).item() == pytest.approx(2.5)
    assert masked_mse(pred, target, torch.zeros_like(mask)).item() == 0.0

    a = torch.arange(8.0).reshape(2, 4, 1).expand(2, 4, 2)
    filled = fill_padding(a, torch.tensor([[True, True, False, False], [False, True, False, True]]))
    assert filled[0, :, 0].tolist() == [0.0, 1.0, 1.0, 1.0]  # as ChunkDataset pads: the last real step repeats
    assert filled[1, :, 0].tolist() == [5.0, 5.0, 5.0, 7.0]


def _chunk_batch(b: int = 6, h: int = 8, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    obs = np.stack(
        [
            observation_keypoints(
                (*rng.uniform(100, 400, 2), rng.uniform(-3, 3)), (256, 256, 0.8), rng.uniform(50, 450, 2)
            )
            for _ in range(b)
        ]
    )
    actions = obs[:, None, -1] + np.cumsum(rng.normal(0, 10, (b, h, 2)), axis=1)
    mask = np.arange(h)[None] < rng.integers(1, h + 1, b)[:, None]
    mask[0] = True
    return {
        "obs": torch.tensor(obs, dtype=torch.float32),
        "actions": torch.tensor(actions, dtype=torch.float32),
        "mask": torch.tensor(mask),
    }


@pytest.mark.parametrize("goal_frame", [False, True])
def test_padded_actions_do_not_change_the_loss(goal_frame):
    torch.manual_seed(0)
    model = pusht_kcfm(goal_frame, horizon=8)
    batch = _chunk_batch()
    model.processor.fit(batch["obs"].numpy(), batch["actions"][:, 0].numpy())
    assert not batch["mask"].all()

    def loss(b):
        return model.loss(b, generator=torch.Generator().manual_seed(1)).item()

    reference = loss(batch)
    garbage = dict(batch, actions=torch.where(batch["mask"][..., None], batch["actions"], torch.tensor(1e4)))
    assert loss(garbage) == reference  # bit for bit: padded values never reach the network or the loss
    real = batch["actions"].clone()
    real[0, 0] += 50.0
    assert loss(dict(batch, actions=real)) != reference
    # the same generator seed gives the same loss, another one another
    assert model.loss(batch, generator=torch.Generator().manual_seed(2)).item() != reference


@pytest.mark.parametrize("goal_frame", [False, True])
def test_relative_actions_are_offsets_from_the_agent(goal_frame):
    model = pusht_kcfm(goal_frame, horizon=8, relative=True)
    batch = _chunk_batch()
    kp, actions, mask = batch["obs"].double(), batch["actions"].double(), batch["mask"]
    model.processor.fit(kp, actions, mask)
    frame = model.processor.action_frame(kp)
    torch.testing.assert_close(frame[1], kp[:, -1])  # the origin is the agent
    x = model.processor.normalise_actions(actions, frame)
    assert x[mask].abs().max() <= 1.0 + 1e-6 and x[mask].min(0).values.allclose(torch.tensor(-1.0), atol=1e-5)
    torch.testing.assert_close(model.processor.denormalise_actions(x, frame).double(), actions, atol=1e-3, rtol=0)
    # the statistics only count real steps: padded garbage does not change them
    before = model.processor.action_scale.clone()
    model.processor.fit(kp, torch.where(mask[..., None], actions, torch.tensor(1e4, dtype=torch.float64)), mask)
    torch.testing.assert_close(model.processor.action_scale, before)
    moved = kp.clone()
    moved[:, -1] += torch.tensor([30.0, -12.0], dtype=torch.float64)  # the agent elsewhere: the same offsets
    shifted = model.processor.denormalise_actions(x, model.processor.action_frame(moved)).double()
    torch.testing.assert_close(shifted - moved[:, None, -1], actions - kp[:, None, -1], atol=1e-3, rtol=0)
    with pytest.raises(ValueError, match="2-D actions"):
        pusht_kcfm(action_dim=3, relative=True)


# ---------------------------------------------------------------------------------------------- goal frame


def test_goal_pose_is_exact():
    """Push-T's goal frame (its goal T's keypoints and body template) fits the goal T's pose exactly."""
    model = pusht_kcfm(True)
    poses = [(256.0, 256.0, math.pi / 4), (-40.0, 700.0, -2.9), (10.0, 20.0, 0.0)]
    kp = torch.tensor(np.stack([observation_keypoints((300.0, 100.0, 1.0), pose, (5.0, 6.0)) for pose in poses]))
    rot, origin = model.processor.goal_pose(kp)
    torch.testing.assert_close(origin, torch.tensor(poses, dtype=torch.float64)[:, :2], atol=1e-9, rtol=0)
    np.testing.assert_allclose(
        torch.atan2(rot[:, 1, 0], rot[:, 0, 0]).numpy(), [p[2] for p in poses], atol=1e-12, rtol=0
    )


def test_the_goal_frame_names_the_goal_keypoints_and_their_template():
    good = pusht_goal_frame()
    for bad, message in (
        (True, "goal_frame must be None or"),
        ({"keypoints": good["keypoints"]}, "goal_frame must be None or"),
        (dict(good, keypoints=[12, 12] + good["keypoints"][2:]), "distinct indices in 0..24"),
        (dict(good, keypoints=[0, 25] + good["keypoints"][2:]), "distinct indices in 0..24"),
        (dict(good, keypoints=[0.0] + good["keypoints"][1:]), "must list keypoint indices"),
        (dict(good, template=good["template"][:-1]), r"must hold 12 finite points \[x, y\]"),
        (dict(good, template=[[1.0, 2.0]] * 12), "is one point"),
    ):
        with pytest.raises(ValueError, match=message):
            KCFM(N_KEYPOINTS, processor={"goal_frame": bad})
    with pytest.raises(ValueError, match="planar"):
        KCFM(N_KEYPOINTS, keypoint_dim=3, processor={"goal_frame": good})
    with pytest.raises(ValueError, match="2-D actions"):
        KCFM(N_KEYPOINTS, action_dim=3, processor={"goal_frame": good})
    # any planar layout: the goal's keypoints anywhere among them, its template in its own frame
    model = KCFM(4, horizon=4, processor={"goal_frame": {"keypoints": [3, 1], "template": [[0.0, 0.0], [2.0, 0.0]]}})
    rot, origin = model.processor.goal_pose(
        torch.tensor([[[9.0, 9.0], [5.0, 7.0], [0.0, 0.0], [5.0, 5.0]]], dtype=torch.float64)
    )
    torch.testing.assert_close(origin, torch.tensor([[5.0, 5.0]], dtype=torch.float64))  # the goal turned a quarter
    torch.testing.assert_close(rot, torch.tensor([[[0.0, -1.0], [1.0, 0.0]]], dtype=torch.float64))


def _scene_keypoints(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)

    def pose(lo: float, hi: float) -> tuple:
        return (*rng.uniform(lo, hi, 2), rng.uniform(-3, 3))

    return np.stack([observation_keypoints(pose(100, 400), pose(150, 350), rng.uniform(50, 450, 2)) for _ in range(n)])


@pytest.mark.parametrize("goal_frame", [True, False])
def test_goal_frame_policy_is_equivariant(goal_frame):
    """Rotating and translating the whole scene rotates and translates the predicted chunk identically (same noise)."""
    torch.manual_seed(0)
    model = pusht_kcfm(goal_frame, horizon=20).eval()
    train_kp = _scene_keypoints(64, seed=1)
    model.processor.fit(train_kp, train_kp[:, -1] + 20.0)  # realistic scales
    kp = _scene_keypoints(4, seed=2)
    phi, shift = 2.1, np.array([-130.0, 415.0])
    rot = np.array([[math.cos(phi), -math.sin(phi)], [math.sin(phi), math.cos(phi)]])
    moved = kp @ rot.T + shift

    pred = model.sample(kp, steps=10, generator=torch.Generator().manual_seed(3)).double().numpy()
    pred_moved = model.sample(moved, steps=10, generator=torch.Generator().manual_seed(3)).double().numpy()
    gap = np.abs(pred_moved - (pred @ rot.T + shift)).max()
    if goal_frame:
        assert gap < 1e-3  # px; measured 8e-5 (float32 network, float64 frames)
    else:
        assert gap > 1.0  # measured ~1400 px: the world-frame model is not equivariant: the check above has teeth


def test_an_origin_keypoint_makes_a_3d_policy_translation_invariant():
    """With ``origin`` (a gripper's keypoint), translating the whole 3-D scene translates the chunk's positions by the
    same vector and leaves its other values (rotation, gripper) as they were (same noise); the range check is made
    relative to the origin, so the scene moved far from the training data is still accepted."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    k, d, a = 6, 3, 10
    train_kp = rng.uniform(-0.3, 0.3, (64, k, d))
    chunks = np.concatenate(
        [train_kp[:, None, -3] + rng.normal(0, 0.05, (64, 8, d)), rng.normal(0, 1, (64, 8, a - d))], -1
    )
    model = KCFM(k, horizon=8, keypoint_dim=d, action_dim=a, processor={"origin": -3}).eval()
    model.processor.fit(train_kp, chunks)
    kp, shift = train_kp[:4], np.array([20.0, -15.0, 7.0])  # moved far outside the training box
    pred = model.sample(kp, steps=5, generator=torch.Generator().manual_seed(3)).double().numpy()
    moved = model.sample(kp + shift, steps=5, generator=torch.Generator().manual_seed(3)).double().numpy()
    np.testing.assert_allclose(moved[..., :d], pred[..., :d] + shift, atol=1e-5)
    np.testing.assert_allclose(moved[..., d:], pred[..., d:], atol=1e-6)
    world = KCFM(k, horizon=8, keypoint_dim=d, action_dim=a).eval()
    world.processor.fit(train_kp, chunks)
    model.check_in_range(kp + shift)
    with pytest.raises(ValueError, match="far outside the range"):
        world.check_in_range(kp + shift)  # the world-frame model refuses what the origin-relative one accepts
    bad = kp.copy()
    bad[0, 0] += 500.0
    with pytest.raises(ValueError, match="relative to keypoint -3"):
        model.check_in_range(bad)
    with pytest.raises(ValueError, match="relative to keypoint -3"):  # sample checks the same when given a margin
        model.sample(bad, steps=1, input_margin=INPUT_MARGIN)
    with pytest.raises(ValueError, match="far outside the range"):
        world.sample(kp + shift, steps=1, input_margin=INPUT_MARGIN)
    assert world.sample(kp + shift, steps=1).shape == (4, 8, a)  # and nothing without one
    for kwargs, message in (
        ({"origin": 6}, "keypoint index"),
        ({"origin": True}, "keypoint index"),
        ({"origin": 0, "relative": True}, "without goal_frame"),
    ):
        with pytest.raises(ValueError, match=message):
            KCFM(k, keypoint_dim=2, action_dim=2, processor=kwargs)


# ------------------------------------------------------------------------------------------- input checks


def test_sample_validates_steps_and_keypoints():
    model = pusht_kcfm(horizon=6).eval()
    kp = _scene_keypoints(2, seed=0)
    assert model.sample(kp[0], steps=1).shape == (1, 6, 2)  # an unbatched observation gives a batch of one
    out = model.sample(
        torch.tensor(kp, dtype=torch.float32), steps=MAX_STEPS, generator=torch.Generator().manual_seed(0)
    )
    assert out.shape == (2, 6, 2) and out.dtype == torch.float32
    torch.testing.assert_close(model.sample(kp, steps=MAX_STEPS, generator=torch.Generator().manual_seed(0)), out)
    assert not torch.equal(model.sample(kp, steps=MAX_STEPS, generator=torch.Generator().manual_seed(1)), out)
    for steps in (0, MAX_STEPS + 1, -3, 2.5, True, "10"):
        with pytest.raises(ValueError, match="steps must be an integer"):
            model.sample(kp, steps=steps)
    for bad in (
        kp[0, :24],
        kp[..., :1],
        kp[0, :, 0],
        np.zeros((0, 25, 2)),
        np.zeros((1, 2, 25, 2)),
    ):  # n_obs = 1: one frame per item
        with pytest.raises(ValueError, match="keypoints must have shape"):
            model.sample(bad)
    nan = kp.copy()
    nan[1, 24, 0] = np.nan
    with pytest.raises(ValueError, match=r"NaN or inf \(batch items \[1\]\)"):
        model.sample(nan)
    with pytest.raises(ValueError, match="array of numbers"):
        model.sample([[1.0, 2.0], [3.0]])


# ------------------------------------------------------------------------------------- training end to end

H = 8


def _trainer(tmp_path, max_steps: int) -> lightning.Trainer:
    return lightning.Trainer(
        max_steps=max_steps,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=True,
        default_root_dir=tmp_path,
        enable_progress_bar=False,
        enable_model_summary=False,
        check_val_every_n_epoch=10,
    )


@pytest.mark.slow
def test_train_sample_checkpoint_reload_and_resume(tmp_path):
    path = tmp_path / "demos.zarr"
    walk_to_block_store(path)
    lightning.seed_everything(0, verbose=False)
    model = pusht_kcfm(horizon=H, optim={"lr": 3e-3})
    datamodule = ChunkDataModule(path, horizon=H, batch_size=64)
    trainer = _trainer(tmp_path, max_steps=300)
    model.fit_processor(datamodule.training_chunks())
    trainer.fit(model, datamodule=datamodule)
    assert trainer.global_step == 300
    assert {"train/loss", "val/loss"} <= set(trainer.callback_metrics)

    # the normalisation came from the training episodes only
    train_set = datamodule.train_set
    rows = np.concatenate(
        [np.arange(s.start, s.stop) for s in map(EpisodeStore(path).episode_slice, datamodule.train_episodes)]
    )
    lo, hi = train_set.actions[rows].min(0), train_set.actions[rows].max(0)
    torch.testing.assert_close(model.processor.action_center, torch.tensor((lo + hi) / 2))
    torch.testing.assert_close(model.processor.action_scale, torch.tensor((hi - lo) / 2))

    items = [train_set[i] for i in range(len(train_set))]
    batch = {k: torch.stack([it[k] for it in items]) for k in ("obs", "actions", "mask")}
    model.eval()

    # the loss falls clearly: trained vs. the same model untrained (same normalisation, same noise draws)
    fresh = KCFM(**model.hparams)
    fresh.load_state_dict(
        {k: v for k, v in model.state_dict().items() if not k.startswith(("net.", "ema_net."))}, strict=False
    )
    with torch.no_grad():
        before = fresh.loss(batch, generator=torch.Generator().manual_seed(1)).item()
        after = model.loss(batch, net=model.ema_net, generator=torch.Generator().manual_seed(1)).item()
    assert after < 0.2 * before, (before, after)  # measured: 1.36 -> 0.10

    # 10 Euler steps reproduce the deterministic chunks roughly (after only 300 steps; ~3 px after 1000)
    def chunk_error(policy: KCFM) -> torch.Tensor:
        pred = policy.sample(batch["obs"], steps=10, generator=torch.Generator().manual_seed(0))
        return (pred - batch["actions"]).norm(dim=-1)[batch["mask"]]

    err, untrained = chunk_error(model), chunk_error(fresh)
    # measured: median 24 px (p90 67) vs 260 px untrained
    assert err.median() < 35.0 and err.median() < 0.25 * untrained.median(), (err.median(), untrained.median())

    # checkpoint -> reload on CPU -> identical samples for the same generator seed
    ckpt = tmp_path / "kcfm.ckpt"
    trainer.save_checkpoint(ckpt)
    from kpflow.utils.checkpoint import load_checkpoint

    loaded = load_checkpoint(KCFM, ckpt)
    assert not loaded.training and loaded.hparams.horizon == H
    kp = batch["obs"][:5]
    assert torch.equal(
        loaded.sample(kp, generator=torch.Generator().manual_seed(7)),
        model.sample(kp, generator=torch.Generator().manual_seed(7)),
    )
    for name, p in model.ema_net.state_dict().items():
        assert torch.equal(p, loaded.ema_net.state_dict()[name])  # the EMA weights travel in the checkpoint

    # resume: global_step continues; the checkpoint's normalisation and EMA are kept and the EMA keeps moving
    resumed = pusht_kcfm(horizon=H, optim={"lr": 3e-3})
    trainer2 = _trainer(tmp_path, max_steps=310)
    trainer2.fit(resumed, datamodule=ChunkDataModule(path, horizon=H, batch_size=64), ckpt_path=ckpt)
    assert trainer2.global_step == 310
    torch.testing.assert_close(resumed.processor.action_center, loaded.processor.action_center)
    torch.testing.assert_close(resumed.processor.kp_std, loaded.processor.kp_std)
    moved = [not torch.equal(p, q) for p, q in zip(resumed.ema_net.parameters(), loaded.ema_net.parameters())]
    assert any(moved)
