"""K-CFM behind the Policy protocol, and K-CFM transported online (Eq. 5): seeding, checkpoints, the identity and
rigid-motion properties of ``phi(f(phi^-1(x)))``, and what transport buys a trained K-CFM on a moved scene.

Real K-CFMs (a tiny one trained by Lightning on a synthetic episode store, and untrained ones with fixed
normalisation for the properties that hold whatever the weights) and real ILWR maps; no mocks."""

import math

import lightning
import numpy as np
import pytest
import torch

from kpflow.core.policy import Policy
from kpflow.data.chunks import ChunkDataModule
from kpflow.data.episode_store import EpisodeStore
from kpflow.data.source_index import SourceIndex
from kpflow.maps import AffineMap, ILWRMap
from kpflow.policies.kcfm.model import KCFM
from kpflow.policies.kcfm.policy import KCFMPolicy
from kpflow.policies.kcfm.sampling import MAX_STEPS
from kpflow.policies.transported_kcfm import TransportedKCFMPolicy
from kpflow.tasks.pusht.geometry import N_KEYPOINTS, PUSHT_BLOCK, pusht_weights
from kpflow.tasks.pusht.task import PushTTask
from tests.helpers import bare_kcfm, load_kcfm, walk_to_block_store

PUSHT = PushTTask.policy_layout  # the transporting policies need the task's layout (Push-T: the agent is the robot)

H = 8


def _rigid(angle: float, shift) -> tuple[np.ndarray, np.ndarray]:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]]), np.asarray(shift, dtype=np.float64)


@pytest.fixture(scope="module")
def store_path(tmp_path_factory):
    """Episodes where the agent walks straight to the block's centre, as in test_kcfm (tests.helpers.walk_to_block_store)."""
    path = tmp_path_factory.mktemp("kcfm_demos") / "demos.zarr"
    walk_to_block_store(path)
    return path


@pytest.fixture(scope="module")
def index(store_path):
    """Every training configuration, compared in the block's frame (so a rigidly moved scene finds its original)."""
    return SourceIndex.from_store(
        EpisodeStore(store_path), horizon=H, weights=pusht_weights(agent=4.0), reference=PUSHT_BLOCK
    )


@pytest.fixture(scope="module")
def untrained(index):
    """A world-frame K-CFM with random weights and the data's normalisation: not equivariant by itself."""
    torch.manual_seed(0)
    model = KCFM(N_KEYPOINTS, horizon=H).eval()
    model.processor.fit(index.keypoints, index.chunks[:, 0])
    return model


@pytest.fixture(scope="module")
def trained(store_path, tmp_path_factory):
    """A tiny world-frame K-CFM trained for 250 steps on all episodes, and its checkpoint."""
    root = tmp_path_factory.mktemp("kcfm_run")
    lightning.seed_everything(0, verbose=False)
    model = KCFM(N_KEYPOINTS, horizon=H, optim={"lr": 3e-3})
    trainer = lightning.Trainer(
        max_steps=250,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        default_root_dir=root,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
    )
    data = ChunkDataModule(store_path, horizon=H, batch_size=64, val_fraction=0.0)
    model.fit_processor(data.training_chunks())
    trainer.fit(model, datamodule=data)
    ckpt = root / "kcfm.ckpt"
    trainer.save_checkpoint(ckpt)
    return model.eval(), ckpt


def _obs(keypoints) -> dict:
    return {"keypoints": np.asarray(keypoints, dtype=np.float64)}


# ------------------------------------------------------------------------------------------------ KCFMPolicy


def test_kcfm_policy_shapes_and_seeding(untrained, index):
    policy = KCFMPolicy(untrained, steps=4, execute=5)
    assert isinstance(policy, Policy)
    obs = _obs(index.keypoints[30])
    policy.reset(3)
    first, second = policy.act(obs), policy.act(obs)
    assert first.shape == (5, 2) and first.dtype == np.float64 and np.isfinite(first).all()
    assert not np.array_equal(first, second)  # the generator moves on within an episode
    policy.reset(3)
    np.testing.assert_array_equal(policy.act(obs), first)  # same seed, same episode
    policy.reset(4)
    assert np.abs(policy.act(obs) - first).max() > 1e-2  # another seed, other noise
    policy.reset(None)
    none = policy.act(obs)
    policy.reset(0)
    np.testing.assert_array_equal(policy.act(obs), none)  # None means 0
    # exactly the model's sample with a generator seeded the same way
    expected = untrained.sample(obs["keypoints"], 4, torch.Generator().manual_seed(0))[0, :5].double().numpy()
    np.testing.assert_array_equal(none, expected)


def test_bad_arguments_raise(untrained, index):
    for kwargs in (
        {"execute": 0},
        {"execute": H + 1},
        {"execute": 2.5},
        {"execute": True},
        {"steps": 0},
        {"steps": MAX_STEPS + 1},
    ):
        name = next(iter(kwargs))
        with pytest.raises(ValueError, match=name):
            KCFMPolicy(untrained, **kwargs)
        with pytest.raises(ValueError, match=name):
            TransportedKCFMPolicy(untrained, index, **kwargs, layout=PUSHT)
    assert KCFMPolicy(untrained, execute=H).act(_obs(index.keypoints[0])).shape == (H, 2)
    with pytest.raises(ValueError, match="index holds keypoints"):
        TransportedKCFMPolicy(untrained, SourceIndex(index.keypoints[:, :24], index.chunks), layout=PUSHT)
    policy = TransportedKCFMPolicy(untrained, index, layout=PUSHT)
    with pytest.raises(ValueError, match="shape"):
        policy.act(_obs(index.keypoints[0, :24]))
    with pytest.raises(FileNotFoundError):
        bare_kcfm("/nonexistent/kcfm.ckpt")


@pytest.mark.slow
def test_checkpoint_round_trip_gives_identical_actions(trained, index):
    model, ckpt = trained
    for make in (
        lambda: (KCFMPolicy(model, 10, 6), bare_kcfm(ckpt, 10, 6)),
        lambda: (
            TransportedKCFMPolicy(model, index, execute=6, layout=PUSHT),
            TransportedKCFMPolicy(load_kcfm(ckpt), index, execute=6, layout=PUSHT),
        ),
    ):
        live, loaded = make()
        assert not loaded.model.training and loaded.model.device.type == "cpu"
        live.reset(11)
        loaded.reset(11)
        moved = index.keypoints[45] @ _rigid(0.7, (20.0, -35.0))[0].T + (20.0, -35.0)
        for kp in (index.keypoints[12], moved):
            a, b = live.act(_obs(kp)), loaded.act(_obs(kp))
            assert a.shape == (6, 2)
            np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------------------- TransportedKCFMPolicy


def test_observing_a_source_makes_phi_the_identity(untrained, index):
    """T = S: phi is the identity, so the transported chunk is K-CFM's own chunk at S for the same noise."""
    transported = TransportedKCFMPolicy(untrained, index, steps=10, execute=H, layout=PUSHT)
    plain = KCFMPolicy(untrained, steps=10, execute=H)
    assert isinstance(transported, Policy)
    for k in (0, 37, 101, len(index) - 1):
        obs = _obs(index.keypoints[k])
        transported.reset(k)
        plain.reset(k)
        chunk = transported.act(obs)
        assert chunk.shape == (H, 2) and chunk.dtype == np.float64
        np.testing.assert_allclose(chunk, plain.act(obs), atol=1e-3, rtol=0)  # px; measured 2e-13
        assert transported.last_source == k
        np.testing.assert_allclose(transported.last_pullback, obs["keypoints"], atol=1e-6, rtol=0)
        grid = torch.from_numpy(np.mgrid[0:512:64, 0:512:64].reshape(2, -1).T.astype(np.float64))
        with torch.no_grad():
            np.testing.assert_allclose(transported.last_map(grid).numpy(), grid.numpy(), atol=1e-6, rtol=0)
    transported.reset()
    assert transported.last_source is None and transported.last_map is None and transported.last_pullback is None


@pytest.mark.parametrize(("angle", "shift"), [(0.6, (40.0, -25.0)), (2.4, (-180.0, 330.0))])
def test_rigid_motion_of_the_scene_moves_the_chunk_rigidly(untrained, index, angle, shift):
    """Rotate and translate all 25 keypoints of a source: ILWR's rigid alignment absorbs the motion, K-CFM sees the
    source again and the chunk comes out moved the same way, although the world-frame K-CFM is not equivariant."""
    rot, shift = _rigid(angle, shift)
    transported = TransportedKCFMPolicy(untrained, index, execute=H, layout=PUSHT)
    plain = KCFMPolicy(untrained, execute=H)
    for k in (5, 88):
        source = index.keypoints[k].astype(np.float64)
        moved = _obs(source @ rot.T + shift)
        transported.reset(1)
        chunk = transported.act(moved)
        assert transported.last_source == k
        np.testing.assert_allclose(transported.last_pullback, source, atol=1e-4, rtol=0)
        plain.reset(1)
        expected = plain.act(_obs(source)) @ rot.T + shift
        np.testing.assert_allclose(chunk, expected, atol=1e-2, rtol=0)  # px; measured 2e-13
        plain.reset(1)
        assert (
            np.abs(plain.act(moved) - expected).max() > 1.0
        )  # without transport it is not moved along (measured 270-950 px)


def test_a_rigid_map_family_works_too(untrained, index):
    """Any map with an inverse can be plugged in; a rigid one reproduces the rigid-motion property exactly."""
    rot, shift = _rigid(-1.3, (100.0, 60.0))
    source = index.keypoints[60].astype(np.float64)
    transported = TransportedKCFMPolicy(untrained, index, make_map=AffineMap, execute=4, layout=PUSHT)
    plain = KCFMPolicy(untrained, execute=4)
    transported.reset(2)
    plain.reset(2)
    np.testing.assert_allclose(
        transported.act(_obs(source @ rot.T + shift)), plain.act(_obs(source)) @ rot.T + shift, atol=1e-2
    )


def test_transport_keeps_a_trained_kcfm_accurate_on_a_moved_scene(trained, index):
    """Training scenes moved rigidly out of the training range: the demonstrated chunk moves with the scene. The
    transported K-CFM keeps its in-distribution accuracy there; the plain K-CFM, seeing unseen inputs, does not."""
    model, _ = trained
    rot, shift = _rigid(2.0, (380.0, -260.0))
    transported = TransportedKCFMPolicy(model, index, make_map=ILWRMap, execute=H, layout=PUSHT)
    plain = KCFMPolicy(model, execute=H)
    rows = np.arange(0, len(index), 7)
    errs = {"in_dist": [], "transported": [], "plain": []}
    for k in rows:
        source, truth = index.keypoints[k].astype(np.float64), index.chunks[k].astype(np.float64)
        moved, moved_truth = source @ rot.T + shift, truth @ rot.T + shift
        for name, policy, kp, want in (
            ("in_dist", plain, source, truth),
            ("transported", transported, moved, moved_truth),
            ("plain", plain, moved, moved_truth),
        ):
            policy.reset(int(k))
            errs[name].append(np.linalg.norm(policy.act(_obs(kp)) - want, axis=-1).mean())
    med = {name: float(np.median(e)) for name, e in errs.items()}
    assert med["transported"] == pytest.approx(med["in_dist"], abs=1e-2), med  # the same chunks, moved rigidly
    # measured: 28.1 px mean chunk error in distribution and transported, 421 px for the plain K-CFM on the moved scenes
    assert med["transported"] < 40.0 and med["transported"] < 0.25 * med["plain"], med


def test_the_kcfm_sees_the_source_scene_with_the_robot_pulled_back(untrained, index):
    """pull_back="agent": block and goal are the source's exactly, the agent is phi^-1(observed agent);
    pull_back="all": every observed keypoint goes through phi^-1."""
    source = index.keypoints[30].astype(np.float64)
    observed = source.copy()
    observed[:24] += np.random.default_rng(0).normal(0.0, 3.0, (24, 2))  # the scene a little off the source
    observed[-1] += (6.0, -4.0)
    agent = TransportedKCFMPolicy(untrained, index, execute=H, layout=PUSHT)
    agent.reset(0)
    agent.act(_obs(observed))
    i = agent.last_source
    np.testing.assert_array_equal(agent.last_pullback[:-1], index.keypoints[i, :-1].astype(np.float64))
    with torch.no_grad():
        back = agent.last_map.inverse(torch.from_numpy(observed[-1:]))[0].numpy()
    np.testing.assert_allclose(agent.last_pullback[-1], back, atol=1e-9)
    every = TransportedKCFMPolicy(untrained, index, execute=H, pull_back="all", layout=PUSHT)
    every.reset(0)
    every.act(_obs(observed))
    with torch.no_grad():
        back = every.last_map.inverse(torch.from_numpy(observed)).numpy()
    np.testing.assert_allclose(every.last_pullback, back, atol=1e-9)
    with pytest.raises(ValueError, match="pull_back"):
        TransportedKCFMPolicy(untrained, index, pull_back="scene", layout=PUSHT)


def test_built_with_reach_and_turn_it_searches_and_acts_on_the_shown_goal(trained, store_path):
    """``policy.reach`` / ``policy.turn_deg`` wrap the transported K-CFM in :class:`SubgoalPolicy`: the source search
    and the K-CFM see the goal moved within reach and turn, so it acts exactly as the plain policy on that observation."""
    from kpflow.policies.factory import transported_kcfm
    from kpflow.policies.subgoal import SubgoalPolicy
    from kpflow.tasks.pusht.geometry import observation_keypoints
    from kpflow.tasks.pusht.task import PushTTask

    _, ckpt = trained
    demos = ChunkDataModule(store_path, horizon=H)
    TRANSPORT = {"search": {"weights": {"agent": 4.0}, "frame": "block"}, "fit_on": ["block", "agent"]}
    wrapped = transported_kcfm(str(ckpt), demos, PushTTask(), transport=TRANSPORT, reach=60.0, turn_deg=20.0)
    plain = transported_kcfm(str(ckpt), demos, PushTTask(), transport=TRANSPORT)
    assert isinstance(wrapped, SubgoalPolicy) and isinstance(wrapped.policy, TransportedKCFMPolicy)
    assert isinstance(plain, TransportedKCFMPolicy)
    obs = _obs(
        observation_keypoints((300.0, 250.0, 0.3), (150.0, 150.0, 2.5), (240.0, 320.0))
    )  # goal 180 px off, turned 2.2 rad
    shown = wrapped.shown(obs)
    assert not np.allclose(shown["keypoints"], obs["keypoints"])
    wrapped.reset(3), plain.reset(3)
    np.testing.assert_array_equal(wrapped.act(obs), plain.act(shown))
    assert wrapped.policy.last_source == plain.last_source == plain.index.query(shown["keypoints"])[0]
    assert plain.index.query(obs["keypoints"])[0] != plain.last_source  # the observed goal would find another source
