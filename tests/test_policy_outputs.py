"""A robot never receives NaN (issue 40). Every K-CFM policy (plain, transported, within reach and turn), in process and
served, refuses observations far outside its training data before the network runs, and refuses actions that come out
NaN or inf, with a ValueError (an error reply over the wire, the connection kept) naming the cause. Planted: every
keypoint at 1e300 px (finite), and a real checkpoint whose last layer's finite weights overflow to inf. Push-T's
evaluation splits (object_ood, robot_ood: the large workspace) stay accepted by the released checkpoints. Real
K-CFMs (the released ones, a tiny one trained here), real servers on port 0; no mocks."""

from pathlib import Path

import lightning
import numpy as np
import pytest
import torch

from kpflow.data.chunks import ChunkDataModule
from kpflow.data.episode_store import EpisodeStore
from kpflow.data.source_index import SourceIndex
from kpflow.policies.checks import INPUT_MARGIN, check_actions
from kpflow.policies.factory import source_index_path
from kpflow.policies.kcfm.model import KCFM
from kpflow.policies.kcfm.policy import KCFMPolicy
from kpflow.policies.subgoal import SubgoalPolicy
from kpflow.policies.transported_kcfm import TransportedKCFMPolicy
from kpflow.serving import PolicyClient, PolicyServer, PolicyServerError, load_deployment
from kpflow.tasks.pusht.env import PushTEnv
from kpflow.tasks.pusht.geometry import (
    N_KEYPOINTS,
    PUSHT_BLOCK,
    PUSHT_GOAL,
    goal_frame,
    observation_keypoints,
    pusht_weights,
)
from kpflow.tasks.pusht.rollout import run_episode
from kpflow.tasks.pusht.scene import split_config
from kpflow.tasks.pusht.task import PushTTask
from kpflow.utils.checkpoint import load_checkpoint
from tests.helpers import StandStill, bare_kcfm, walk_to_block_store

PUSHT = PushTTask.policy_layout  # the transporting policies need the task's layout (Push-T: the agent is the robot)

ROOT = Path(__file__).resolve().parents[1]
RELEASED = sorted((ROOT / "release").glob("pusht_*.ckpt"))
STANDARD = ROOT / "release" / "pusht_standard_kcfm_human.ckpt"
H = 8
FAR = "far outside the range this K-CFM was trained on"
NOT_FINITE = r"produced \d+ NaN or inf action value\(s\)"
HUGE = {"keypoints": np.full((25, 2), 1e300)}


def scene(seed: int = 0) -> dict:
    """An ordinary in-distribution Push-T observation."""
    c = split_config("in_distribution", seed)
    return {"keypoints": observation_keypoints(c.block_pose, c.goal_pose, c.agent_pos)}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A world-frame K-CFM trained for 2 steps on synthetic episodes (checkpoint), its source index beside it, and a
    copy whose EMA network's last layer is scaled by 1e37: finite weights (the load accepts them) that overflow."""
    root = tmp_path_factory.mktemp("outputs")
    walk_to_block_store(root / "demos.zarr")
    lightning.seed_everything(0, verbose=False)
    trainer = lightning.Trainer(max_steps=2, accelerator="cpu", logger=False, enable_checkpointing=False, default_root_dir=root,
                                enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0)  # fmt: skip
    model, data = (
        KCFM(N_KEYPOINTS, horizon=H),
        ChunkDataModule(root / "demos.zarr", horizon=H, batch_size=64, val_fraction=0.0),
    )
    model.fit_processor(data.training_chunks())
    trainer.fit(model, datamodule=data)
    good = root / "good" / "kcfm.ckpt"
    good.parent.mkdir()
    trainer.save_checkpoint(good)
    index = SourceIndex.from_store(
        EpisodeStore(root / "demos.zarr"), horizon=H, weights=pusht_weights(agent=4.0), reference=PUSHT_BLOCK
    )
    index.save(source_index_path(good))
    checkpoint = torch.load(good, weights_only=True)
    checkpoint["state_dict"]["ema_net.final.1.weight"] *= 1e37
    overflow = root / "overflow" / "kcfm.ckpt"
    overflow.parent.mkdir()
    torch.save(checkpoint, overflow)
    index.save(source_index_path(overflow))
    return good, overflow, index


def counting(model: KCFM) -> list:
    """A list that grows by one per call of ``model``'s EMA network (a forward hook)."""
    calls = []
    model.ema_net.register_forward_hook(lambda *_: calls.append(1))
    return calls


def test_extreme_observations_are_refused_before_the_network_runs(tiny):
    """1e300 px everywhere, or only the agent 1e5 px away: every K-CFM policy raises naming the training range, and the
    network is never called. The released goal-frame K-CFM too (checked in the world and in the goal's frame)."""
    good, _, index = tiny
    model = load_checkpoint(KCFM, good)
    calls = counting(model)
    policies = [KCFMPolicy(model, 2, 4), TransportedKCFMPolicy(model, index, steps=2, execute=4, layout=PUSHT),
                SubgoalPolicy(KCFMPolicy(model, 2, 4), PUSHT_BLOCK, PUSHT_GOAL, 60.0)]  # fmt: skip
    agent_away = scene()["keypoints"].copy()
    agent_away[24] = (1e5, 200.0)
    for policy in policies:
        for obs, match in (
            (HUGE, "keypoint 0 at \\(1e\\+300, 1e\\+300\\)"),
            ({"keypoints": agent_away}, "keypoint 24 at \\(1e\\+05, 200\\)"),
        ):
            with pytest.raises(ValueError, match=f"{FAR}: {match}"):
                policy.act(obs)
    turned = SubgoalPolicy(KCFMPolicy(model, 2, 4), PUSHT_BLOCK, PUSHT_GOAL, 60.0, 30.0)
    with pytest.raises(
        ValueError,
        match=r"obs\['keypoints'\] is too large to move its goal within reach and turn: it overflowed \(largest coordinate 1e\+300\)",
    ):
        turned.act(HUGE)  # the goal's turn overflows float64 before the K-CFM sees it
    with pytest.raises(ValueError, match=f"{FAR}: keypoint 24"):
        turned.act({"keypoints": agent_away})
    assert not calls
    assert policies[0].act(scene()).shape == (4, 2) and len(calls) == 2  # an ordinary scene runs the network (2 steps)
    released = bare_kcfm(STANDARD, steps=2)
    assert released.model.config.processor.goal_frame == goal_frame()
    with pytest.raises(ValueError, match=f"{FAR}: keypoint 0 at"):
        released.act(HUGE)  # in its goal's frame this scene is ordinary: the world check refuses it
    # every coordinate within the widened box in the world, but the agent 7920 px from the goal in the goal's frame
    apart = observation_keypoints((250.0, 250.0, 0.0), (-2800.0, -2800.0, np.pi / 4), (2800.0, 2800.0))
    with pytest.raises(
        ValueError, match=f"{FAR}: keypoint 24 at \\(2800, 2800\\) has coordinate 0 = 7920 in the goal's frame"
    ):
        released.act({"keypoints": apart})


def test_without_the_range_check_extreme_observations_give_non_finite_actions_that_are_refused(tiny):
    """input_margin=None turns the range check off: the 1e300 scene then reaches the network, whose chunk comes out
    NaN or inf (the failure on main), and the output check refuses it instead of returning it."""
    good, _, _ = tiny
    policy = bare_kcfm(good, steps=2, execute=4, input_margin=None)
    calls = counting(policy.model)
    with pytest.raises(ValueError, match=f"the K-CFM {NOT_FINITE} of 8"):
        policy.act(HUGE)
    assert calls  # the network did run: the output check caught it
    with pytest.raises(ValueError, match="input_margin must be a finite number >= 0 or null; got -1"):
        bare_kcfm(good, input_margin=-1)


def test_a_model_whose_output_overflows_is_refused(tiny):
    """The planted checkpoint loads (its weights are finite) but its chunks overflow: the plain, transported and
    wrapped policies raise naming NaN or inf actions; the same scene with the original weights acts."""
    good, overflow, index = tiny
    obs = {"keypoints": index.keypoints[10].astype(np.float64)}
    for path, fine in ((good, True), (overflow, False)):
        model = load_checkpoint(KCFM, path)
        for policy in (KCFMPolicy(model, 2, 4), TransportedKCFMPolicy(model, index, steps=2, execute=4, layout=PUSHT),
                       SubgoalPolicy(KCFMPolicy(model, 2, 4), PUSHT_BLOCK, PUSHT_GOAL, 60.0)):  # fmt: skip
            if fine:
                assert np.isfinite(policy.act(obs)).all()
            else:
                with pytest.raises(ValueError, match=f"the K-CFM {NOT_FINITE}"):
                    policy.act(obs)


def test_the_wrapper_checks_what_any_policy_returns():
    """SubgoalPolicy around a policy that does not check its own actions (StandStill returns obs["agent_pos"]) refuses
    an inf it returns, naming itself, and an observation with NaN or too large to move its goal; the shared check names
    the steps."""
    wrapped = SubgoalPolicy(StandStill(), PUSHT_BLOCK, PUSHT_GOAL, 60.0)
    obs = {**scene(), "agent_pos": np.array([[0.0, 1.0], [np.inf, 2.0]])}
    with pytest.raises(
        ValueError,
        match=r"the policy within reach and turn produced 1 NaN or inf action value\(s\) of 4 \(steps \[1\]\)",
    ):
        wrapped.act(obs)
    np.testing.assert_array_equal(wrapped.act({**obs, "agent_pos": np.zeros((2, 2))}), np.zeros((2, 2)))
    apart = np.concatenate(
        [np.full((12, 2), -1e308), np.full((12, 2), 1e308), np.zeros((1, 2))]
    )  # goal - block overflows
    with pytest.raises(
        ValueError, match=r"obs\['keypoints'\] is too large to move its goal within reach and turn: it overflowed"
    ):
        wrapped.act({"keypoints": apart, "agent_pos": np.zeros((2, 2))})
    with pytest.raises(ValueError, match=r"obs\['keypoints'\] holds 1 NaN or inf value\(s\)"):
        wrapped.act(
            {
                "keypoints": np.where(np.arange(50).reshape(25, 2) == 7, np.nan, scene()["keypoints"]),
                "agent_pos": np.zeros((2, 2)),
            }
        )
    with pytest.raises(ValueError, match=r"x produced 1 NaN or inf action value\(s\) of 3 \(steps \[2\]\)"):
        check_actions([1.0, 2.0, np.nan], "x")


def test_served_policies_reply_with_an_error_naming_the_cause(tiny):
    """Through real servers: the 1e300 scene (plain and transported K-CFM) and the overflowing checkpoint get error
    replies naming the cause, and each connection goes on serving."""
    good, overflow, _ = tiny
    ilwr, rigid = {"kind": "transported_kcfm"}, {"kind": "transported_kcfm", "transport": {"map": "affine"}}
    for path, kind, obs, match in ((good, {}, HUGE, FAR), (good, ilwr, HUGE, FAR),
                                   (overflow, {}, scene(), NOT_FINITE), (overflow, rigid, scene(), NOT_FINITE)):  # fmt: skip
        deployment = load_deployment(path, PushTTask(), {**kind, "steps": 2, "execute": 4})
        with PolicyServer(deployment, port=0).running() as address, PolicyClient(address) as client:
            with pytest.raises(PolicyServerError, match=match):
                client.act(obs)
            client.reset(1)  # the connection stays open
            if path == good:
                assert np.isfinite(client.act(scene())).all()
            else:
                with pytest.raises(PolicyServerError, match=NOT_FINITE):
                    client.act(scene())
    deployment = load_deployment(good, PushTTask(), {"steps": 2, "execute": 4}, input_margin=None)
    with PolicyServer(deployment, port=0).running() as address, PolicyClient(address) as client:
        with pytest.raises(PolicyServerError, match=NOT_FINITE):  # no range check: the output check still holds
            client.act(HUGE)


@pytest.mark.parametrize("checkpoint", RELEASED, ids=lambda p: p.stem)
def test_released_checkpoints_accept_the_evaluation_splits(checkpoint):
    """The first 200 evaluation configurations (10000...) of object_ood and robot_ood (the 1024-px workspace), and of
    in_distribution, are within every released K-CFM's range at the default margin; so is any scene inside the large
    workspace (its corners); a short real episode on each OOD split acts throughout."""
    model = load_checkpoint(KCFM, checkpoint)
    for split in ("object_ood", "robot_ood", "in_distribution"):
        for i in range(10000, 10200):
            c = split_config(split, i)
            model.check_in_range(observation_keypoints(c.block_pose, c.goal_pose, c.agent_pos), INPUT_MARGIN)
    for block, goal, agent in (
        ((1000.0, 1000.0, 2.0), (24.0, 24.0, 0.0), (0.0, 1024.0)),
        ((24.0, 1000.0, -1.0), (1000.0, 24.0, 3.0), (1024.0, 0.0)),
    ):
        model.check_in_range(observation_keypoints(block, goal, agent), INPUT_MARGIN)
    policy = KCFMPolicy(model, steps=2, execute=8)
    for split in ("object_ood", "robot_ood"):
        result = run_episode(PushTEnv(split=split), policy, split_config(split, 10000), max_steps=16, seed=0)
        assert result.steps == 16


def test_policies_refuse_a_seed_that_is_not_an_integer(tiny):
    """reset(1.5) used to seed 1: in process as on the client (tests/test_serving.py), a K-CFM, a transported K-CFM and
    policy transportation's source choice refuse it, naming the seed; numpy integers are integers."""
    good, _, index = tiny
    model = load_checkpoint(KCFM, good)
    for policy in (KCFMPolicy(model, 2, 4), TransportedKCFMPolicy(model, index, steps=2, execute=4, layout=PUSHT)):
        for seed in (1.5, True, "1", -1):
            with pytest.raises(ValueError, match=f"seed must be an integer >= 0 or null; got {seed!r}"):
                policy.reset(seed)
        policy.reset(np.int64(3))
        first = policy.act(scene())
        policy.reset(3)
        np.testing.assert_array_equal(policy.act(scene()), first)
