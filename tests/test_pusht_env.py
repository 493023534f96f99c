"""Push-T: physics facts, keypoints, coverage, reset splits, the Gymnasium API and rendering (real pymunk/shapely)."""

import math
import re
import warnings

import gymnasium as gym
import imageio.v2 as imageio
import numpy as np
import pymunk
import pytest
import shapely
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from kpflow.geometry.alignment import fit_affine
from kpflow.geometry.angles import wrap_angle
from kpflow.tasks.pusht import (
    ENV_IDS,
    FIXED_GOAL,
    KEYPOINT_NAMES,
    SPLITS,
    STANDARD_FIRST_SEED,
    Config,
    PushTEnv,
    PushTPhysics,
    coverage,
    get_workspace,
    make_split,
    split_config,
    standard_config,
    t_keypoints,
)
from kpflow.tasks.pusht.geometry import (
    AGENT_RADIUS,
    OUTLINE,
    T_AREA,
    T_KEYPOINTS,
    outline_coverage,
    t_polygon,
    to_world,
)
from kpflow.tasks.pusht.physics import block_mass_properties
from kpflow.tasks.pusht.render import AGENT, BLOCK, GOAL, KEYPOINT, REGION, WHITE
from kpflow.utils.video import write_video

STANDARD = get_workspace("standard")


def physics(agent, block, workspace=STANDARD, physically_correct=False) -> PushTPhysics:
    p = PushTPhysics(workspace, physically_correct)
    p.set_state(agent, block)
    return p


def angle_diff(a, b) -> float:
    return float(abs(wrap_angle(a - b)))


# ================================================================================================ physics


def test_agent_pushing_the_flank_moves_the_block_in_the_push_direction():
    # Block at (256, 256, 0): the bar spans x in [196, 316], y in [256, 286]. The agent comes from the left at
    # y = 271 (the bar's mid-height) and pushes +x.
    p = physics((130.0, 271.0), (256.0, 256.0, 0.0))
    start = p.block_pose.copy()
    for k in range(1, 21):
        p.step((130.0 + 5.0 * k, 271.0))
    moved = p.block_pose - start
    assert moved[0] > 20.0  # pushed along +x ...
    assert abs(moved[1]) < 0.2 * moved[0]  # ... mostly along x (a frictionless flat face pushes along its normal)
    assert p.agent_pos[0] < to_world(p.block_pose, OUTLINE)[:, 0].min()  # the agent stayed on the pushing side


def test_the_block_stops_as_soon_as_contact_ends():
    p = physics((130.0, 271.0), (256.0, 256.0, 0.0))
    for k in range(1, 16):
        p.step((130.0 + 5.0 * k, 271.0))
    pushed = p.block_pose.copy()
    assert pushed[0] > 256.0 + 10.0
    p.step((100.0, 150.0))  # retreat: contact ends during this step
    assert shapely.distance(t_polygon(p.block_pose), shapely.Point(p.agent_pos)) > AGENT_RADIUS
    after_retreat = p.block_pose.copy()
    assert np.linalg.norm(after_retreat[:2] - pushed[:2]) < 2.0  # coasts at most ~one substep, no momentum
    for _ in range(10):
        p.step((100.0, 150.0))
        np.testing.assert_array_equal(p.block_pose, after_retreat)  # no velocity of its own: exactly at rest
    assert p.block.velocity.length == 0.0 and p.block.angular_velocity == 0.0


def push_slowly(p, start, end, n=120):
    """Move the agent's target from ``start`` to ``end`` at 2 px per step; yields the T outline after each step."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    for k in range(1, n + 1):
        p.step(start + np.clip(end - start, -2.0 * k, 2.0 * k))
        yield to_world(p.block_pose, OUTLINE)


def wall_gap(outline) -> float:
    """Smallest distance of a T vertex inside the standard walls' centre lines (negative: beyond them)."""
    return min(outline.min() - STANDARD.wall_lo, STANDARD.wall_hi - outline.max())


WALL_PUSHES = {  # agent start, block pose, agent target end: a free block would end up beyond the wall
    "left, through the cog": ((185.0, 301.0), (150.0, 256.0, 0.0), (80.0, 301.0)),
    "left, on the bar": ((185.0, 271.0), (150.0, 256.0, 0.0), (80.0, 271.0)),
    "left, far past": ((185.0, 301.0), (150.0, 256.0, 0.0), (30.0, 301.0)),
    "right, tilted": ((330.0, 250.0), (380.0, 200.0, 0.3), (480.0, 250.0)),
}


@pytest.mark.parametrize("case", WALL_PUSHES)
def test_walls_hold_the_block(case):
    """The agent slowly pushes the block into a wall and on past it: the block slides and turns along the wall."""
    start, block, end = WALL_PUSHES[case]
    gaps = [wall_gap(outline) for outline in push_slowly(physics(start, block), start, end)]
    assert min(gaps) > 0.0  # every T vertex inside the walls, every step
    assert min(gaps) < 5.0  # and it did reach a wall
    free = physics(start, block)
    free.space.remove(*free.space.static_body.shapes)  # the same push without walls leaves the arena
    assert min(wall_gap(outline) for outline in push_slowly(free, start, end)) < -10.0


def test_walls_hold_the_block_squeezed_head_on():
    """Pushing the stem straight up into the top wall squeezes the block between the kinematic agent (infinite
    mass) and the wall. pymunk's soft contacts then let the bar dip a few px into the wall for some steps before
    the block slides out sideways; it never crosses it and comes to rest against it (the standard env does the same).
    """
    start, end = (256.0, 300.0), (256.0, 100.0)  # a free block's bar would end at y = -35
    p = physics(start, (256.0, 150.0, 0.0))
    tops = np.array([outline[:, 1].min() for outline in push_slowly(p, start, end)])
    assert tops.min() > STANDARD.wall_lo - 6.0  # bounded dip, the bar's edge stays in the wall's band
    assert abs(tops[-1] - (STANDARD.wall_lo + 2.0)) < 0.2  # at rest against the wall's surface (radius 2)
    assert abs(p.block_pose[2]) < 1e-6 and abs(p.block_pose[0] - 256.0) > 15.0  # slid along the wall


def test_the_kinematic_agent_passes_through_walls():
    p = physics((100.0, 256.0), (350.0, 300.0, 0.0))
    for _ in range(20):
        p.step((-40.0, 256.0))
    assert p.agent_pos[0] < STANDARD.wall_lo - AGENT_RADIUS  # the whole disc is beyond the left wall
    assert abs(p.agent_pos[0] + 40.0) < 0.1


def test_the_agent_tracks_a_held_target_critically_damped():
    target = np.array([300.0, 150.0])
    p = physics((100.0, 100.0), (400.0, 400.0, 0.0))
    start = p.agent_pos.copy()
    dist, prev = [], np.inf
    for k in range(20):
        p.step(target)
        pos = p.agent_pos
        dist.append(np.linalg.norm(pos - target))
        # never past the target by more than 1 px along either axis (critically damped: no overshoot)
        assert np.all((pos - target) * np.sign(target - start) <= 1.0)
        assert dist[-1] <= prev + 1e-9  # monotone approach
        prev = dist[-1]
    assert dist[0] > 50.0  # it does take time: a 200-px jump is not done in one step
    assert dist[7] < 1.0  # within 1 px after 8 control steps (0.8 s)
    assert dist[14] < 0.01


@pytest.mark.parametrize("physically_correct", [False, True])
def test_set_state_puts_the_body_origin_exactly_at_the_pose(physically_correct):
    p = PushTPhysics(STANDARD, physically_correct)
    body_point = np.array([15.0, 120.0])
    for theta in (0.0, 0.3, -1.2, math.pi / 2, math.pi, 2.9, 5.5):
        pose = (231.5, 277.25, theta)
        p.set_state((50.0, 50.0), pose)  # from whatever angle the previous iteration left
        assert np.allclose(p.block_pose, pose, rtol=0, atol=1e-9)
        assert np.allclose(tuple(p.block.local_to_world((0.0, 0.0))), pose[:2], rtol=0, atol=1e-9)
        assert np.allclose(tuple(p.block.local_to_world(tuple(body_point))), to_world(pose, body_point), atol=1e-9)
    # Why the order matters: pymunk rotates about the centre of gravity, so position-then-angle misses.
    p.set_state((50.0, 50.0), (231.5, 277.25, 0.0))
    p.block.position = (231.5, 277.25)
    p.block.angle = 1.0
    assert np.linalg.norm(np.array(p.block.position) - (231.5, 277.25)) > 10.0


def test_block_mass_properties():
    bar_moment = pymunk.moment_for_poly(1.0, [(-60, 30), (60, 30), (60, 0), (-60, 0)])
    assert bar_moment == pytest.approx(1500.0)  # (120^2 + 30^2) / 12 + 15^2 about the body origin
    moment, cog = block_mass_properties(False)
    assert moment == pytest.approx(2.0 * bar_moment) and cog == (0.0, 45.0)
    p = PushTPhysics(STANDARD)
    assert p.block.mass == 1.0 and p.block.moment == pytest.approx(3000.0)
    assert tuple(p.block.center_of_gravity) == (0.0, 45.0)

    moment, cog = block_mass_properties(True)
    y = (3600 * 15 + 2700 * 75) / 6300  # area-weighted centroid: 40.714...
    assert cog[0] == pytest.approx(0.0, abs=1e-12) and cog[1] == pytest.approx(y, abs=1e-9)
    assert cog[1] == pytest.approx(40.714285714, abs=1e-8)
    m1, m2 = 3600 / 6300, 2700 / 6300  # parallel axis theorem about the centre of gravity
    expected = m1 * ((120**2 + 30**2) / 12 + (y - 15) ** 2) + m2 * ((30**2 + 90**2) / 12 + (75 - y) ** 2)
    assert moment == pytest.approx(expected, rel=1e-9)
    p = PushTPhysics(STANDARD, physically_correct=True)
    assert p.block.moment == pytest.approx(expected, rel=1e-9)
    assert tuple(p.block.center_of_gravity) == pytest.approx((0.0, y))


# ================================================================================================ keypoints

DOCUMENTED = [
    (-60, 0), (60, 0), (60, 30), (-60, 30), (0, 0), (0, 30),
    (-15, 30), (15, 30), (15, 120), (-15, 120), (-15, 75), (15, 75),
]  # fmt: skip


def random_pushes(env, n, rng):
    """Targets that chase the block's centre with noise, so that the agent pushes it around."""
    obs, _ = env.reset(seed=int(rng.integers(1 << 30)))
    yield obs
    for _ in range(n):
        centre = obs["keypoints"][:12].mean(0)
        obs, *_ = env.step(centre + rng.normal(0.0, 25.0, 2))
        yield obs


def test_keypoints_follow_the_block_pose_exactly():
    env = PushTEnv()
    rng = np.random.default_rng(0)
    first, moved, goal_kp = None, 0.0, None
    for obs in random_pushes(env, 60, rng):
        kp = obs["keypoints"]
        assert kp.shape == (25, 2) and kp.dtype == np.float64
        np.testing.assert_allclose(kp[:12], t_keypoints(obs["block_pose"]), rtol=0, atol=1e-9)
        np.testing.assert_allclose(kp[:12], t_keypoints(env.physics.block_pose), rtol=0, atol=1e-9)
        if goal_kp is None:
            goal_kp, first = kp[12:24].copy(), obs["block_pose"].copy()
        np.testing.assert_array_equal(kp[12:24], goal_kp)  # the goal never moves
        np.testing.assert_allclose(kp[12:24], t_keypoints(obs["goal_pose"]), rtol=0, atol=1e-9)
        np.testing.assert_array_equal(kp[24], obs["agent_pos"])
        moved = max(moved, np.linalg.norm(obs["block_pose"][:2] - first[:2]))
    assert moved > 10.0  # the pushes really moved the block


def test_keypoint_order_matches_the_names_and_the_documented_coordinates():
    assert len(KEYPOINT_NAMES) == 25 and len(set(KEYPOINT_NAMES)) == 25
    assert KEYPOINT_NAMES[8] == "block_stem_corner_2" and KEYPOINT_NAMES[20] == "goal_stem_corner_2"
    assert KEYPOINT_NAMES[0].startswith("block_bar") and KEYPOINT_NAMES[12].startswith("goal_bar")
    assert KEYPOINT_NAMES[24] == "agent"
    assert all(n.startswith("block_") for n in KEYPOINT_NAMES[:12])
    assert [n[len("block_") :] for n in KEYPOINT_NAMES[:12]] == [n[len("goal_") :] for n in KEYPOINT_NAMES[12:24]]
    np.testing.assert_array_equal(T_KEYPOINTS, np.array(DOCUMENTED, float))
    np.testing.assert_array_equal(t_keypoints((0.0, 0.0, 0.0)), T_KEYPOINTS)
    np.testing.assert_allclose(t_keypoints((10.0, 20.0, math.pi / 2))[8], (10.0 - 120.0, 20.0 + 15.0), atol=1e-12)
    # corners of the bar and stem are on the boxes' corners, the mids on their long edges
    for i, name in enumerate(KEYPOINT_NAMES[:12]):
        x, y = DOCUMENTED[i]
        if "bar" in name:
            assert abs(x) <= 60 and 0 <= y <= 30
        else:
            assert abs(x) == 15 and 30 <= y <= 120
    env = PushTEnv(goal="fixed")
    obs, _ = env.reset(options={"state": [60.0, 60.0, 200.0, 180.0, 0.7]})
    np.testing.assert_allclose(obs["keypoints"][8], to_world((200.0, 180.0, 0.7), np.array([15.0, 120.0])), atol=1e-9)
    np.testing.assert_allclose(obs["keypoints"][20], to_world(FIXED_GOAL, np.array([15.0, 120.0])), atol=1e-9)
    np.testing.assert_array_equal(obs["keypoints"][24], (60.0, 60.0))


def test_the_twelve_keypoints_are_distinct():
    for pose in [(0.0, 0.0, 0.0), (256.0, 256.0, 2.3)]:
        kp = t_keypoints(pose)
        d = np.linalg.norm(kp[:, None] - kp[None], axis=-1)
        assert d[~np.eye(12, dtype=bool)].min() >= 15.0 - 1e-9


def test_the_pose_is_recovered_from_the_keypoints_by_a_rigid_fit():
    rng = np.random.default_rng(3)
    src = torch.tensor(T_KEYPOINTS, dtype=torch.float64)[None]
    for _ in range(10):
        pose = np.array([*rng.uniform(0.0, 512.0, 2), rng.uniform(-np.pi, np.pi)])
        a, t = fit_affine(src, torch.tensor(t_keypoints(pose))[None], "rigid")
        a, t = a[0].numpy(), t[0].numpy()
        np.testing.assert_allclose(t, pose[:2], rtol=0, atol=1e-6)  # the body origin is the keypoints' frame origin
        assert angle_diff(math.atan2(a[1, 0], a[0, 0]), pose[2]) < 1e-6
        assert abs(np.linalg.det(a) - 1.0) < 1e-9  # a rotation, not a reflection


# ================================================================================================ coverage


def test_coverage_values():
    g = np.array(FIXED_GOAL)
    assert coverage(g, g) == pytest.approx(1.0, abs=1e-12)
    assert coverage(g + (2.0, 0.0, 0.0), g) == pytest.approx(0.9468, abs=0.002)  # standard env's table: ~0.947
    assert coverage(g + (0.0, 2.0, 0.0), g) == pytest.approx(0.9468, abs=0.002)
    assert coverage(g + (0.0, 0.0, math.radians(5)), g) == pytest.approx(0.8547, abs=0.002)  # ~0.85
    assert coverage(g + (0.0, 0.0, -math.radians(5)), g) == pytest.approx(0.8547, abs=0.002)
    assert coverage(g + (200.0, 0.0, 0.0), g) == 0.0  # disjoint bounding boxes: the early-out
    # interlocked Ts 2 px apart: their bounding boxes overlap, so shapely computes the (empty) intersection
    block, goal = (288.0, 408.0, math.pi), (256.0, 256.0, 0.0)
    assert shapely.intersects(t_polygon(block).envelope, t_polygon(goal).envelope)
    assert t_polygon(block).distance(t_polygon(goal)) == pytest.approx(2.0)
    assert coverage(block, goal) == 0.0


@pytest.mark.parametrize("goal_angle", [math.pi / 4, 0.0, 2.5])
def test_coverage_is_symmetric_and_monotone_in_the_shift(goal_angle):
    g = np.array([256.0, 256.0, goal_angle])
    for direction in [(1.0, 0.0), (0.0, 1.0), (0.6, 0.8), (-0.6, 0.8)]:
        d = np.array([*direction, 0.0])
        shifts = np.linspace(0.0, 20.0, 41)
        cov = np.array([coverage(g + s * d, g) for s in shifts])
        back = np.array([coverage(g - s * d, g) for s in shifts])
        np.testing.assert_allclose(cov, back, rtol=0, atol=1e-9)
        assert np.all(np.diff(cov) < 0.0)
        assert cov[-1] < 0.7


def test_outline_coverage_equals_a_direct_shapely_computation():
    rng = np.random.default_rng(5)
    nonzero = 0
    for _ in range(100):
        goal = (*rng.uniform(150.0, 350.0, 2), rng.uniform(-np.pi, np.pi))
        block = np.array(goal) + (*rng.normal(0.0, 30.0, 2), rng.normal(0.0, 0.5))
        goal_outline, block_outline = to_world(goal, OUTLINE), to_world(block, OUTLINE)
        direct = shapely.Polygon(goal_outline).intersection(shapely.Polygon(block_outline)).area / 6300.0
        assert outline_coverage(block_outline, t_polygon(goal)) == pytest.approx(direct, abs=1e-12)
        assert coverage(block, goal) == pytest.approx(direct, abs=1e-12)
        nonzero += direct > 0
    assert nonzero > 50
    assert t_polygon(FIXED_GOAL).area == pytest.approx(T_AREA) and T_AREA == 6300.0


# ================================================================================================ splits


@pytest.mark.parametrize("split", SPLITS)
def test_make_split_is_reproducible(split):
    a, b = make_split(split, 20, seed=1), make_split(split, 20, seed=1)
    assert a == b
    assert make_split(split, 5, seed=1) == a[:5]  # config i does not depend on n
    assert split_config(split, 13, seed=1) == a[13]
    assert all(x != y for x, y in zip(make_split(split, 20, seed=2), a))
    assert len({c.block_pose for c in a}) == 20


def _in_region(points, region=512.0):
    return np.all((points >= 0.0) & (points <= region))


@pytest.mark.parametrize("split", SPLITS)
def test_splits_satisfy_their_definitions(split):
    configs = make_split(split, 200, seed=0)
    assert len(configs) == 200
    for c in configs:
        assert isinstance(c, Config)
        ws = get_workspace(c.workspace)
        agent, block = np.array(c.agent_pos), np.array(c.block_pose)
        outline = to_world(block, OUTLINE)
        assert _in_region(to_world(c.goal_pose, OUTLINE))  # the goal T is inside the 512 training region
        assert ws.in_walls(outline).all()  # the T is inside the walls
        assert shapely.distance(t_polygon(block), shapely.Point(agent)) > AGENT_RADIUS  # agent not touching
        assert coverage(block, c.goal_pose) < 0.85  # not solved at the start
        if split == "in_distribution":
            assert c.workspace == "standard"
            assert np.all((agent >= 50.0) & (agent <= 450.0))
            assert np.all((block[:2] >= 100.0) & (block[:2] <= 400.0))
        elif split == "robot_ood":
            assert c.workspace == "large"
            nearest = np.clip(agent, 0.0, 512.0)  # closest point of the training region to the agent's centre
            assert np.linalg.norm(agent - nearest) > AGENT_RADIUS  # the disc is completely outside it
            assert ws.in_walls(agent[None], margin=AGENT_RADIUS).all()
            assert np.all((block[:2] >= 100.0) & (block[:2] <= 400.0))
        else:
            assert c.workspace == "large"
            assert not _in_region(outline)  # at least one T vertex outside the training region
    if split == "object_ood":  # some completely outside, some partially
        inside = [np.all((to_world(c.block_pose, OUTLINE) <= 512.0), axis=1).sum() for c in configs]
        assert min(inside) == 0 and max(inside) > 0


@pytest.mark.parametrize("split", SPLITS)
def test_fixed_goal_mode(split):
    for c in make_split(split, 10, seed=0, goal="fixed"):
        assert c.goal_pose == (256.0, 256.0, math.pi / 4)
    assert FIXED_GOAL == (256.0, 256.0, math.pi / 4)
    assert len({c.goal_pose for c in make_split(split, 10, seed=0)}) == 10  # random goals differ


def test_bad_split_and_goal_names_raise():
    with pytest.raises(ValueError, match="in_distribution.*robot_ood.*object_ood"):
        make_split("ood", 5)
    with pytest.raises(ValueError, match="random.*fixed"):
        make_split("in_distribution", 5, goal="centre")
    with pytest.raises(ValueError, match="in_distribution"):
        PushTEnv(split="ood")
    with pytest.raises(ValueError, match="random.*fixed"):
        PushTEnv(goal="centre")


# ================================================================================================ env API


@pytest.mark.parametrize("split", SPLITS)
def test_gymnasium_check_env_passes(split):
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(PushTEnv(split=split, render_mode="rgb_array"), skip_render_check=False)
    # Benign: absolute pixel targets are not a [-1, 1] box by design; no spec without gymnasium.make.
    benign = ("symmetric and normalized space", "not having a spec")
    assert [str(w.message) for w in caught if not any(b in str(w.message) for b in benign)] == []


@pytest.mark.parametrize("env_id", sorted(ENV_IDS))
def test_registered_ids_make_checked_envs_with_a_time_limit(env_id):
    from gymnasium.utils.env_checker import check_env

    kwargs, limit = ENV_IDS[env_id]
    env = gym.make(env_id, render_mode="rgb_array")
    assert (
        env.spec.max_episode_steps == limit
        and env.unwrapped.split == kwargs["split"]
        and env.render_mode == "rgb_array"
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped, skip_render_check=False)
    assert [str(w.message) for w in caught if "symmetric and normalized space" not in str(w.message)] == []
    spaces = (env.observation_space, env.action_space)
    obs, _ = env.reset(seed=1)
    for step in range(1, limit + 1):  # the agent holds still: TimeLimit truncates at the registered limit
        obs, _, terminated, truncated, info = env.step(obs["agent_pos"])
        assert not terminated and truncated == (step == limit)
        if step in (1, limit):
            assert env.observation_space.contains(obs)
    assert (env.observation_space, env.action_space) == spaces and env.render().shape == (512, 512, 3)


def test_the_standard_id_resets_to_diffusion_policys_start_states():
    env = gym.make("kpflow/PushT-v0")
    for seed in (STANDARD_FIRST_SEED, STANDARD_FIRST_SEED + 1, 7):
        obs, _ = env.reset(seed=seed)
        c = standard_config(seed)
        np.testing.assert_allclose(obs["agent_pos"], c.agent_pos, atol=1e-6)
        np.testing.assert_allclose(obs["goal_pose"], FIXED_GOAL, atol=1e-12)
        assert angle_diff(obs["block_pose"][2], c.block_pose[2]) < 1e-9
    env.reset(seed=0)
    assert env.render() is None  # render_mode defaults to None


def test_reset_with_a_seed_is_reproducible():
    def rollout(seed):
        env = PushTEnv(max_steps=10)
        obs, _ = env.reset(seed=seed)
        out = [obs["keypoints"].copy()]
        rng = np.random.default_rng(0)
        for _ in range(10):
            obs, *_ = env.step(obs["keypoints"][:12].mean(0) + rng.normal(0, 20, 2))
            out.append(obs["keypoints"].copy())
        return np.array(out)

    a = rollout(7)
    np.testing.assert_array_equal(a, rollout(7))
    assert not np.allclose(a[0], rollout(8)[0])
    env = PushTEnv()
    c = make_split("in_distribution", 1, seed=0)[0]
    first, _ = env.reset(seed=7)
    env.reset(options={"config": c})  # seeding again resets the generator
    again, _ = env.reset(seed=7)
    np.testing.assert_array_equal(first["keypoints"], again["keypoints"])


def chase(env, config, n=100, seed=0, actions=None):
    """Reset to ``config`` and push the block around (or replay ``actions``); returns actions and block poses."""
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(options={"config": config})
    taken, poses = [], []
    for k in range(n):
        a = actions[k] if actions is not None else obs["keypoints"][:12].mean(0) + rng.normal(0.0, 30.0, 2)
        obs, *_ = env.step(a)
        taken.append(np.asarray(a, float)), poses.append(env.physics.block_pose)
    return np.array(taken), np.array(poses)


def test_reset_does_not_depend_on_earlier_episodes():
    """pymunk keeps a contact-correction ("bias") velocity after a step with contact; a reset in the middle of a
    push must not carry it (nor anything else) into the next episode: the block starts exactly at the config's pose
    and the same actions give the same trajectory as in a fresh env."""
    configs = make_split("in_distribution", 4, seed=0)
    for k in range(1, 16):  # stop pushing after k steps, most of them in contact
        used = PushTEnv()
        obs, _ = used.reset(seed=1)
        rng = np.random.default_rng(k)
        for _ in range(k):
            obs, *_ = used.step(obs["keypoints"][:12].mean(0) + rng.normal(0.0, 30.0, 2))
        obs, _ = used.reset(options={"config": configs[0]})
        np.testing.assert_array_equal(used.physics.block_pose[:2], configs[0].block_pose[:2])
        assert used.physics.block_pose[2] == configs[0].block_pose[2]
    used = PushTEnv()
    for i in range(1, len(configs)):
        chase(used, configs[i - 1], seed=i)  # an earlier episode with contacts
        actions, fresh = chase(PushTEnv(), configs[i], seed=100 + i)
        _, again = chase(used, configs[i], actions=actions)
        np.testing.assert_array_equal(again, fresh)


def test_reset_to_a_config_places_the_block_in_the_envs_workspace():
    envs = {"standard": PushTEnv(), "large": PushTEnv("object_ood")}
    assert {name: env.workspace.name for name, env in envs.items()} == {"standard": "standard", "large": "large"}
    for c in make_split("object_ood", 3, seed=4) + make_split("in_distribution", 2, seed=4):
        env = envs[c.workspace]
        spaces = (env.observation_space, env.action_space)
        obs, info = env.reset(options={"config": c})
        assert (env.observation_space, env.action_space) == spaces and env.observation_space.contains(obs)
        assert env.workspace.name == c.workspace
        assert env.physics.workspace.name == c.workspace
        np.testing.assert_allclose(obs["block_pose"][:2], c.block_pose[:2], rtol=0, atol=1e-9)
        assert angle_diff(obs["block_pose"][2], c.block_pose[2]) < 1e-9
        np.testing.assert_allclose(obs["goal_pose"][:2], c.goal_pose[:2], rtol=0, atol=1e-12)
        np.testing.assert_allclose(obs["agent_pos"], c.agent_pos, rtol=0, atol=1e-9)
        assert info["coverage"] == pytest.approx(coverage(c.block_pose, c.goal_pose), abs=1e-12)
        assert 0.0 <= obs["block_pose"][2] < 2 * np.pi and 0.0 <= obs["goal_pose"][2] < 2 * np.pi
        if c.workspace == "large":  # the large arena's walls are in place: a T beyond x or y = 506 rests there
            assert (to_world(c.block_pose, OUTLINE) > STANDARD.wall_hi).any()
            assert env.physics.workspace.wall_hi == 1018.0
            obs, *_ = env.step(c.agent_pos)
            np.testing.assert_allclose(obs["block_pose"][:2], c.block_pose[:2], rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="Config"):
        env.reset(options={"config": {"agent_pos": (1, 2)}})
    with pytest.raises(ValueError, match="large workspace but this env's is standard"):
        envs["standard"].reset(options={"config": make_split("robot_ood", 1)[0]})


def test_reset_to_a_state():
    env = PushTEnv()
    obs, info = env.reset(options={"state": [100.0, 120.0, 300.0, 250.0, -0.5]})
    np.testing.assert_allclose(obs["agent_pos"], (100.0, 120.0), atol=1e-9)
    np.testing.assert_allclose(obs["block_pose"], (300.0, 250.0, 2 * np.pi - 0.5), atol=1e-9)
    np.testing.assert_allclose(obs["goal_pose"], FIXED_GOAL, atol=1e-12)
    obs, _ = env.reset(options={"state": [100.0, 120.0, 300.0, 250.0, 0.5], "goal_pose": (200.0, 210.0, 1.0)})
    np.testing.assert_allclose(obs["goal_pose"], (200.0, 210.0, 1.0), atol=1e-12)
    np.testing.assert_allclose(obs["keypoints"][12:24], t_keypoints((200.0, 210.0, 1.0)), atol=1e-9)
    for bad in (
        [1.0, 2.0, 3.0, 4.0],
        [1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
        [1.0, np.nan, 3.0, 4.0, 0.0],
        [1.0, 2.0, np.inf, 4.0, 0.0],
    ):
        with pytest.raises(ValueError, match="state"):
            env.reset(options={"state": bad})


@pytest.mark.parametrize(
    "bad",
    [
        (np.nan, 256.0, 0.0),
        (256.0, np.inf, 0.0),
        (256.0, 256.0, -np.inf),
        (256.0, 256.0),
        (1.0, 2.0, 3.0, 4.0),
        "goal",
        None,
    ],
)
def test_reset_rejects_a_bad_goal_pose(bad):
    env = PushTEnv()
    with pytest.raises(ValueError, match=r"goal_pose must be 3 finite numbers \(goal x, y, angle\), got"):
        env.reset(options={"state": [100.0, 120.0, 300.0, 250.0, 0.5], "goal_pose": bad})


@pytest.mark.parametrize("split, size", [("in_distribution", 512), ("object_ood", 1024)])
def test_reset_rejects_positions_outside_the_arena(split, size):
    env = PushTEnv(split=split)
    name = "standard" if size == 512 else "large"
    good = [100.0, 120.0, 300.0, 250.0, 0.5]
    labels = ["agent x", "agent y", "block x", "block y"]
    for i, label in enumerate(labels):
        for value in (-1.0, size + 1.0, -1e9):
            bad = list(good)
            bad[i] = value
            msg = rf"state\[{i}\] \({label}\) = {re.escape(f'{value:g}')} is outside the {name} arena: positions must lie in \[0, {size}\]"
            with pytest.raises(ValueError, match=msg):
                env.reset(options={"state": bad})
    for i, label in enumerate(["goal x", "goal y"]):
        goal = [256.0, 256.0, 0.0]
        goal[i] = size + 0.5
        with pytest.raises(
            ValueError, match=rf"goal_pose\[{i}\] \({label}\) = {size + 0.5:g} is outside the {name} arena"
        ):
            env.reset(options={"state": good, "goal_pose": goal})
    config = Config((float(size) * 2, 100.0), (300.0, 250.0, 0.0), FIXED_GOAL, name)
    with pytest.raises(
        ValueError, match=rf"config.agent_pos\[0\] \(agent x\) = {2 * size} is outside the {name} arena"
    ):
        env.reset(options={"config": config})
    with pytest.raises(ValueError, match=r"config.block_pose must be 3 finite numbers"):
        env.reset(options={"config": Config((100.0, 100.0), (300.0, np.nan, 0.0), FIXED_GOAL, name)})
    with pytest.raises(ValueError, match=r"state must be 5 finite numbers \(agent x, y, block x, y, angle\)"):
        env.reset(options={"state": [1.0, np.nan, 3.0, 4.0, 0.0]})
    # the arena's edges and any finite angle are fine, and the observation stays in the observation space
    for state in ([0.0, 0.0, 0.0, 0.0, 0.0], [size, size, size, size, 1e6], [size, 0.0, 0.0, size, -7.0]):
        obs, _ = env.reset(options={"state": state, "goal_pose": (size, 0.0, -3.0)})
        assert env.observation_space.contains(obs), state


@settings(max_examples=40)
@given(
    agent=st.tuples(st.floats(0.0, 512.0), st.floats(0.0, 512.0)),
    block=st.tuples(st.floats(0.0, 512.0), st.floats(0.0, 512.0), st.floats(-1e3, 1e3)),
    goal=st.tuples(st.floats(0.0, 512.0), st.floats(0.0, 512.0), st.floats(-1e3, 1e3)),
)
def test_any_state_in_the_arena_gives_an_observation_in_the_observation_space(agent, block, goal):
    env = PushTEnv()
    obs, _ = env.reset(options={"state": [*agent, *block], "goal_pose": goal})
    assert env.observation_space.contains(obs)
    obs, *_ = env.step(agent)
    assert env.observation_space.contains(obs)


def test_reset_rejects_unknown_and_conflicting_options():
    env = PushTEnv()
    known = r"known options are \['config', 'state', 'goal_pose'\]"
    with pytest.raises(ValueError, match=r"unknown reset option\(s\) \['sate'\]; " + known):
        env.reset(options={"sate": [100.0, 120.0, 300.0, 250.0, 0.5]})
    with pytest.raises(ValueError, match=r"unknown reset option\(s\) \['goal', 'seed'\]; " + known):
        env.reset(options={"state": [100.0, 120.0, 300.0, 250.0, 0.5], "seed": 3, "goal": (1, 2, 3)})
    config = make_split("in_distribution", 1, seed=0)[0]
    with pytest.raises(
        ValueError, match=r"options\['config'\] already sets the whole configuration: drop \['goal_pose'\]"
    ):
        env.reset(options={"config": config, "goal_pose": FIXED_GOAL})
    with pytest.raises(ValueError, match=r"drop \['state'\]"):
        env.reset(options={"config": config, "state": [100.0, 120.0, 300.0, 250.0, 0.5]})
    with pytest.raises(ValueError, match=r"options\['goal_pose'\] applies only together with options\['state'\]"):
        env.reset(options={"goal_pose": FIXED_GOAL})
    with pytest.raises(ValueError, match=r"options must be a dict"):
        env.reset(options=[("state", [100.0, 120.0, 300.0, 250.0, 0.5])])
    obs, _ = env.reset(options={})  # empty options: a drawn configuration, as with None
    assert env.observation_space.contains(obs)


def test_step_errors():
    env = PushTEnv()
    with pytest.raises(RuntimeError, match="reset"):
        env.step((100.0, 100.0))
    env.reset(seed=0)
    for bad in ((np.nan, 100.0), (100.0, np.inf), (1.0, 2.0, 3.0)):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    env.step((100.0, 100.0))  # still usable


@pytest.mark.parametrize("threshold", [0.95, 0.85])
def test_success_termination_and_reward(threshold):
    env = PushTEnv(success_threshold=threshold)
    g = np.array(FIXED_GOAL)
    agent = (60.0, 450.0)  # well away from the goal T
    cases = [
        (g, True),
        (g + (2.0, 0.0, 0.0), threshold <= 0.9468),
        (g + (0, 0, math.radians(5)), threshold <= 0.85),
        (g + (30.0, 0.0, 0.0), False),
    ]
    for pose, success in cases:
        env.reset(options={"state": [*agent, *pose]})
        obs, reward, terminated, truncated, info = env.step(agent)
        cov = info["coverage"]
        assert cov == pytest.approx(coverage(pose, g), abs=1e-9)
        assert terminated == info["is_success"] == (cov >= threshold) == success
        assert not truncated
        assert reward == pytest.approx(min(1.0, cov / threshold), abs=1e-12)
        assert info["n_steps"] == 1 and np.array_equal(info["block_pose"], obs["block_pose"])
    # reward along random pushes near the goal
    rng = np.random.default_rng(1)
    obs, _ = env.reset(options={"state": [200.0, 330.0, *(g + (15.0, 10.0, 0.3))]})
    for _ in range(30):
        obs, reward, terminated, _, info = env.step(obs["keypoints"][:12].mean(0) + rng.normal(0, 30, 2))
        assert reward == float(np.clip(info["coverage"] / threshold, 0.0, 1.0))
        assert terminated == (info["coverage"] >= threshold)


def test_truncated_at_max_steps():
    env = PushTEnv(max_steps=5)
    env.reset(options={"state": [60.0, 60.0, 380.0, 200.0, 0.0]})
    for k in range(1, 6):
        _, _, terminated, truncated, info = env.step((60.0, 60.0))
        assert info["n_steps"] == k and not terminated
        assert truncated == (k == 5)
    env.reset(options={"state": [60.0, 60.0, 380.0, 200.0, 0.0]})  # reset restarts the count
    assert not env.step((60.0, 60.0))[3]
    env = PushTEnv(max_steps=1)  # success on the last step: terminated, not truncated
    env.reset(options={"state": [60.0, 450.0, *FIXED_GOAL]})
    _, _, terminated, truncated, _ = env.step((60.0, 450.0))
    assert terminated and not truncated
    env = PushTEnv(max_steps=None)
    env.reset(options={"state": [60.0, 60.0, 380.0, 200.0, 0.0]})
    assert not any(env.step((60.0, 60.0))[3] for _ in range(50))


# ================================================================================================ render


def pixel(img, world_xy, world_size):
    u, v = (np.asarray(world_xy, float) * img.shape[0] / world_size).astype(int)
    return tuple(int(c) for c in img[v, u])


@pytest.mark.parametrize("size", [512, 96])
def test_render_shows_goal_block_and_agent(size):
    env = PushTEnv(render_size=size, render_mode="rgb_array")
    block = (380.0, 80.0, 0.0)  # away from the goal ghost at (256, 256, pi/4)
    env.reset(options={"state": [450.0, 450.0, *block]})
    img = env.render()
    assert img.shape == (size, size, 3) and img.dtype == np.uint8
    assert pixel(img, to_world(FIXED_GOAL, np.array([0.0, 75.0])), 512) == GOAL  # the goal T's stem centre
    assert pixel(img, to_world(FIXED_GOAL, np.array([0.0, 15.0])), 512) == GOAL  # the goal T's bar centre
    assert pixel(img, to_world(block, np.array([0.0, 75.0])), 512) == BLOCK
    assert pixel(img, (450.0, 450.0), 512) == AGENT
    assert pixel(img, (40.0, 450.0), 512) == WHITE
    assert not np.any(np.all(img == KEYPOINT, axis=-1))  # no keypoints unless asked for
    assert PushTEnv().render() is None  # render_mode defaults to None, as Gymnasium asks


def test_render_large_workspace_and_keypoints():
    env = PushTEnv(split="object_ood", render_size=256, render_keypoints=True, render_mode="rgb_array")
    env.reset(options={"state": [800.0, 150.0, 700.0, 700.0, 0.0]})
    assert env.workspace.name == "large"
    img = env.render()
    assert img.shape == (256, 256, 3) and img.dtype == np.uint8
    assert pixel(img, (60.0, 480.0), 1024) == REGION  # the shaded 512-px training region
    assert pixel(img, (900.0, 400.0), 1024) == WHITE
    assert pixel(img, (700.0, 775.0), 1024) == BLOCK
    red = np.all(img == KEYPOINT, axis=-1)
    assert red.sum() > 25
    for x, y in env.physics.block_pose[None, :2].tolist() + [[800.0, 150.0]]:  # dots on keypoints (origin = 4)
        u, v = int(x * 256 / 1024), int(y * 256 / 1024)
        assert red[v - 1 : v + 2, u - 1 : u + 2].any()
    env.step((820.0, 150.0))
    assert env.render().shape == (256, 256, 3)


def test_write_video(tmp_path):
    env = PushTEnv(render_size=96, render_mode="rgb_array")
    env.reset(seed=0)
    frames = [env.render()]
    for k in range(5):
        env.step((100.0 + 10 * k, 100.0))
        frames.append(env.render())
    for suffix in (".mp4", ".gif"):
        path = write_video(frames, tmp_path / f"episode{suffix}", fps=10)
        assert path.exists() and path.stat().st_size > 0
        back = imageio.mimread(path, memtest=False)
        assert len(back) == len(frames)
        assert back[0].shape[:2] == (96, 96)
    for bad in ("episode.avi", "episode.png", "episode"):
        with pytest.raises(ValueError, match="mp4"):
            write_video(frames, tmp_path / bad)
    with pytest.raises(ValueError):
        write_video([], tmp_path / "empty.gif")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode.gif", "episode.mp4"]  # no temporary files left
