"""The goal within reach (kpflow/policies/subgoal.py): closed form of the shift, and a real K-CFM acting on what the
wrapper shows it, with one frame and with a history."""

import numpy as np
import pytest
import torch

from kpflow.policies.kcfm.model import KCFM
from kpflow.policies.kcfm.policy import KCFMPolicy
from kpflow.policies.subgoal import SubgoalPolicy, subgoal_shift, subgoal_turn
from kpflow.tasks.pusht import PushTEnv, split_config
from kpflow.tasks.pusht.geometry import N_KEYPOINTS, PUSHT_BLOCK, PUSHT_GOAL, goal_frame, observation_keypoints
from kpflow.tasks.pusht.rollout import run_episode


def _centroids(kp):
    return kp[list(PUSHT_BLOCK)].mean(0), kp[list(PUSHT_GOAL)].mean(0)


def test_shift_brings_a_far_goal_to_reach_on_the_line_and_leaves_a_near_one():
    far = observation_keypoints((800.0, 700.0, 0.4), (256.0, 256.0, np.pi / 4), (100.0, 100.0))
    block, goal = _centroids(far)
    shift = subgoal_shift(far, PUSHT_BLOCK, PUSHT_GOAL, 200.0)
    moved = far.copy()
    moved[list(PUSHT_GOAL)] += shift
    new_goal = _centroids(moved)[1]
    assert np.linalg.norm(new_goal - block) == pytest.approx(200.0, abs=1e-9)
    np.testing.assert_allclose(new_goal, block + 200.0 * (goal - block) / np.linalg.norm(goal - block), atol=1e-9)
    # a translation: the goal's shape and orientation are kept
    np.testing.assert_allclose(moved[list(PUSHT_GOAL)] - new_goal, far[list(PUSHT_GOAL)] - goal, atol=1e-9)
    distance = np.linalg.norm(goal - block)
    np.testing.assert_array_equal(subgoal_shift(far, PUSHT_BLOCK, PUSHT_GOAL, distance + 1.0), np.zeros(2))


def _turn(kp):
    """The Procrustes angle from the block's centred keypoints to the goal's (radians)."""
    o, g = kp[list(PUSHT_BLOCK)], kp[list(PUSHT_GOAL)]
    o, g = o - o.mean(0), g - g.mean(0)
    return np.arctan2(np.sum(o[:, 0] * g[:, 1] - o[:, 1] * g[:, 0]), np.sum(o * g))


@pytest.mark.parametrize("goal_angle", [np.pi / 4 + 2.5, np.pi / 4 - 2.5, np.pi / 4 + 0.3])
def test_turn_brings_the_goal_within_the_limit_about_its_centre(goal_angle):
    """Block at 0.785 rad, goal turned 2.5 rad either way (or 0.3, within the limit): the goal shown is the goal turned
    about its centroid so that the block needs exactly 60 degrees (the sign kept), its shape and place kept."""
    kp = observation_keypoints((300.0, 280.0, np.pi / 4), (256.0, 256.0, goal_angle), (100.0, 100.0))
    assert _turn(kp) == pytest.approx(goal_angle - np.pi / 4, abs=1e-9)  # the Procrustes angle is the poses' difference
    policy = SubgoalPolicy(KCFMPolicy(_model(1)), PUSHT_BLOCK, PUSHT_GOAL, turn_deg=60.0)
    shown = policy.shown({"keypoints": kp})["keypoints"]
    goal = list(PUSHT_GOAL)
    expected = np.clip(goal_angle - np.pi / 4, -np.pi / 3, np.pi / 3)
    assert _turn(shown) == pytest.approx(expected, abs=1e-9)
    assert subgoal_turn(kp, PUSHT_BLOCK, PUSHT_GOAL, np.pi / 3) == pytest.approx(
        expected - (goal_angle - np.pi / 4), abs=1e-12
    )
    np.testing.assert_allclose(shown[goal].mean(0), kp[goal].mean(0), atol=1e-9)
    np.testing.assert_allclose(
        np.linalg.norm(shown[goal] - shown[goal][:1], axis=1),
        np.linalg.norm(kp[goal] - kp[goal][:1], axis=1),
        atol=1e-9,
    )
    np.testing.assert_array_equal(np.delete(shown, goal, 0), np.delete(kp, goal, 0))  # block and agent as observed
    if abs(goal_angle - np.pi / 4) < np.pi / 3:
        np.testing.assert_allclose(shown, kp, atol=1e-12)


def test_turn_then_reach_on_every_frame():
    """Both limits: the goal turned about its centroid, then moved to within reach; every frame of the history by
    the current frame's turn and shift."""
    kp = observation_keypoints((700.0, 650.0, 0.2), (256.0, 256.0, 0.2 + 3.0), (600.0, 600.0))
    before = kp.copy()
    before[list(PUSHT_BLOCK)] += [4.0, -3.0]  # the block moved; the goal did not
    history = np.stack([before, kp])
    policy = SubgoalPolicy(KCFMPolicy(_model(2)), PUSHT_BLOCK, PUSHT_GOAL, reach=150.0, turn_deg=45.0)
    shown = policy.shown({"keypoints_history": history})["keypoints_history"]
    block, goal = _centroids(shown[-1])
    assert np.linalg.norm(goal - block) == pytest.approx(150.0, abs=1e-9)
    assert _turn(shown[-1]) == pytest.approx(np.pi / 4, abs=1e-9)
    np.testing.assert_allclose(shown[0][list(PUSHT_GOAL)], shown[1][list(PUSHT_GOAL)], atol=1e-12)
    np.testing.assert_array_equal(shown[0][list(PUSHT_BLOCK)], before[list(PUSHT_BLOCK)])


def _model(n_obs: int) -> KCFM:
    torch.manual_seed(0)
    rng = np.random.default_rng(1)
    model = KCFM(
        N_KEYPOINTS,
        horizon=8,
        n_obs=n_obs,
        processor={"goal_frame": goal_frame()},
        network={"name": "unet", "down_dims": [16, 32]},
    ).eval()
    train = np.stack(
        [
            observation_keypoints(
                (*rng.uniform(100, 400, 2), rng.uniform(-3, 3)), (256.0, 256.0, 0.8), rng.uniform(50, 450, 2)
            )
            for _ in range(32)
        ]
    )
    model.processor.fit(train, train[:, -1:] + rng.normal(0.0, 20.0, (32, 8, 2)))
    return model


@pytest.mark.parametrize("n_obs", [1, 2])
def test_policy_acts_on_the_goal_within_reach(n_obs):
    """The wrapped K-CFM returns what the plain one returns for the observation with the goal moved by hand (same
    noise); within reach, exactly what the plain one returns for the observation itself."""
    model = _model(n_obs)
    plain, wrapped = (
        KCFMPolicy(model, steps=3, execute=4),
        SubgoalPolicy(KCFMPolicy(model, steps=3, execute=4), PUSHT_BLOCK, PUSHT_GOAL, 150.0),
    )
    far = observation_keypoints((850.0, 600.0, 1.0), (256.0, 256.0, 0.8), (300.0, 300.0))
    near = observation_keypoints((300.0, 220.0, 1.0), (256.0, 256.0, 0.8), (300.0, 400.0))
    for kp, moves in ((far, True), (near, False)):
        obs = {"keypoints": kp}
        if n_obs > 1:
            obs["keypoints_history"] = np.stack([kp + [5.0, 0.0], kp])
        shown = {k: np.array(v) for k, v in obs.items()}
        shift = subgoal_shift(kp, PUSHT_BLOCK, PUSHT_GOAL, 150.0)
        assert np.linalg.norm(shift) > 100.0 if moves else not shift.any()
        for v in shown.values():
            v[..., list(PUSHT_GOAL), :] += shift  # every frame by the current frame's shift
        plain.reset(5), wrapped.reset(5)
        expected = plain.act(shown)
        np.testing.assert_array_equal(wrapped.act(obs), expected)
        plain.reset(5)
        assert np.array_equal(plain.act(obs), expected) != moves  # the move changes the chunk: the check has teeth


def test_rollout_hands_the_wrapped_policy_its_history():
    """The wrapper says how many frames its policy conditions on, so a real episode hands them over."""
    policy = SubgoalPolicy(KCFMPolicy(_model(2), steps=2, execute=4), PUSHT_BLOCK, PUSHT_GOAL, 100.0)
    assert policy.n_obs == 2
    result = run_episode(PushTEnv(), policy, split_config("in_distribution", 0, 0), max_steps=8, seed=0)
    assert result.steps == 8


def test_bad_reach_and_keypoints_are_refused():
    policy = KCFMPolicy(_model(1))
    for reach in (0.0, -5.0, float("inf"), float("nan"), True, "200"):
        with pytest.raises(ValueError, match="reach must be a positive finite number or None"):
            SubgoalPolicy(policy, PUSHT_BLOCK, PUSHT_GOAL, reach)
        with pytest.raises(ValueError, match="turn_deg must be a positive finite number or None"):
            SubgoalPolicy(policy, PUSHT_BLOCK, PUSHT_GOAL, 100.0, reach)
    with pytest.raises(ValueError, match="in the object's order"):
        SubgoalPolicy(policy, PUSHT_BLOCK, PUSHT_GOAL[:3], turn_deg=30.0)
    with pytest.raises(ValueError, match="none in common"):
        SubgoalPolicy(policy, PUSHT_BLOCK, PUSHT_BLOCK, 100.0)
