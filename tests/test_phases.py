"""Segment-aware online transport (issue 55): a task's phases read from its keypoints (kpflow/policies/phases.py), and
the transported K-CFM following them: in each phase the source is searched among that phase's configurations, the
map is fitted on the phase's declared keypoints and the robot pulled back with what it carries.

Synthetic Stack-like configurations (cube A to pick, cube B to stack it on, the grip site and two finger pads):
before the grasp the jaws are open above cube A; after it they are closed on cube A, above cube B. The last test runs
robosuite's Stack with its scripted demonstration and reads the phase from the keypoints it records.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kpflow.core.phases import Grip, Phase, Phases
from kpflow.core.policy import PolicyLayout
from kpflow.core.symmetry import Symmetry, phase_correspondences, turn_permutation
from kpflow.data.source_index import SourceIndex
from kpflow.geometry.angles import wrap_angle, yaw_of
from kpflow.geometry.rotations import matrix_to_rot6d, rot6d_to_matrix
from kpflow.maps import ILWRMap
from kpflow.policies.kcfm.model import KCFM
from kpflow.policies.transported_kcfm import TransportedKCFMPolicy, source_phases
from kpflow.tasks.suite.arm_limits import SuiteArmLimits
from tests.helpers import cube_corners as _cube
from tests.helpers import random_kcfm_3d
from tests.helpers import yaw_matrix as _yaw

H, K = 8, 19
CUBE_A, CUBE_B, GRIPPER = tuple(range(8)), tuple(range(8, 16)), (16, 17, 18)
GRIP = Grip(pads=(17, 18), grasp_from=CUBE_A, grasp_to=CUBE_A, closed_below=0.07, empty_below=0.01, reach=0.025)
PHASES = Phases(GRIP, (
    Phase("pick", ("cubeA",), ("cubeA",), {"cubeB": 0.0, "gripper": 4.0}, holding=False),
    Phase("place", ("cubeB",), ("cubeB",), {"gripper": 4.0}, carried=("cubeA",), holding=True),
))  # fmt: skip
GROUPS = {"cubeA": CUBE_A, "cubeB": CUBE_B, "gripper": GRIPPER}
ROLES = {"objects": ("cubeA",), "goals": ("cubeB",), "robot": ("gripper",)}
LAYOUT = PolicyLayout(K, 3, 10, GROUPS, ROLES, rotation=True, phases=PHASES)


def _gripper(grip: np.ndarray, yaw: float, gap: float) -> np.ndarray:
    """The grip site and the two finger pads ``gap`` apart across the jaws' yaw."""
    across = _yaw(yaw) @ np.array([0.0, gap / 2, 0.0])
    return np.stack([grip, grip + across, grip - across])


def _scene(rng, holding: bool) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints ``[19, 3]`` and a chunk ``[H, 10]``: open jaws above cube A moving down to it, or jaws closed on cube A
    (lifted) moving over cube B."""
    a = np.r_[rng.uniform(-0.08, 0.08, 2), 0.82]
    b = np.r_[rng.uniform(-0.08, 0.08, 2) + [0.1, 0.0], 0.82]
    yaw = rng.uniform(-0.5, 0.5)
    if holding:
        a = a + [0.0, 0.0, 0.1]
        grip, goal, gap = a.copy(), b + [0.0, 0.0, 0.05], 0.042
    else:
        grip, goal, gap = a + rng.uniform(-0.03, 0.03, 3) + [0.0, 0.0, 0.12], a, 0.085
    keypoints = np.concatenate([_cube(a, yaw), _cube(b, rng.uniform(-0.7, 0.7)), _gripper(grip, yaw, gap)])
    path = grip + np.linspace(0, 1, H)[:, None] * (goal - grip)
    jaws = _yaw(yaw) @ np.diag([1.0, -1.0, -1.0])
    chunk = np.concatenate(
        [path, np.repeat(matrix_to_rot6d(jaws)[None], H, 0), np.full((H, 1), 1.0 if holding else -1.0)], 1
    )
    return keypoints, chunk


@pytest.fixture(scope="module")
def index() -> SourceIndex:
    rng = np.random.default_rng(0)
    scenes = [_scene(rng, holding=i % 2 == 1) for i in range(60)]
    return SourceIndex(
        np.stack([s[0] for s in scenes]), np.stack([s[1] for s in scenes]), LAYOUT.weights({"robot": 4.0}), CUBE_A
    )


@pytest.fixture(scope="module")
def model(index) -> KCFM:
    """A 3-D K-CFM with random weights and the data's normalisation."""
    return random_kcfm_3d(index, K, H, n_obs=1)


def _policy(model, index, segments: bool = True) -> TransportedKCFMPolicy:
    return TransportedKCFMPolicy(model, index, ILWRMap, steps=2, execute=H, layout=LAYOUT, segments=segments,
                                 fit_on=None if segments else LAYOUT.indices("objects", "goals"))  # fmt: skip


def test_a_grip_on_a_segment_holds_anywhere_along_it():
    """A handle from (0, 0, 0) to (0.05, 0, 0): jaws closed at either end or between hold it; beyond its end, or 3 cm
    to its side, they do not (closed form: the distance to the segment)."""
    grip = Grip((1, 2), (3,), (4,), closed_below=0.07, empty_below=0.01, reach=0.02)
    handle = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]])
    cases = {
        (0.0, 0.0): True,
        (0.05, 0.0): True,
        (0.025, 0.0): True,
        (0.065, 0.0): True,
        (0.075, 0.0): False,
        (0.025, 0.03): False,
    }
    keypoints = np.stack([np.concatenate([_gripper(np.array([x, y, 0.0]), 0.0, 0.037), handle]) for x, y in cases])
    np.testing.assert_array_equal(grip.holding(keypoints), list(cases.values()))


def test_the_grip_reads_holding_from_the_pads_and_the_grasp_point():
    cube = _cube([0.0, 0.0, 0.85], 0.3)
    at = np.array([0.0, 0.0, 0.85])
    cases = {
        "closed on the cube": (_gripper(at, 0.3, 0.042), True),
        "open around the cube": (_gripper(at, 0.3, 0.085), False),
        "closed on nothing": (_gripper(at, 0.3, 0.004), False),
        "closed 5 cm beside it": (_gripper(at + [0.05, 0.0, 0.0], 0.3, 0.042), False),
    }
    keypoints = np.stack([np.concatenate([cube, _cube([0.2, 0, 0.82], 0.0), g]) for g, _ in cases.values()])
    np.testing.assert_array_equal(GRIP.holding(keypoints), [held for _, held in cases.values()])
    assert [PHASES.of(k).name for k in keypoints] == ["place", "pick", "pick", "pick"]
    assert PHASES.index(keypoints.reshape(2, 2, K, 3)).shape == (2, 2)  # any batch shape


def test_phases_that_do_not_cover_both_states_or_name_unknown_groups_are_refused():
    pick = Phase("pick", ("cubeA",), ("cubeA",), holding=False)
    with pytest.raises(ValueError, match="exactly one phase must apply while the object is held; none do"):
        Phases(GRIP, (pick,))
    with pytest.raises(ValueError, match="exactly one phase must apply while the object is not held"):
        Phases(GRIP, (pick, Phase("any", ("cubeB",), ("cubeB",))))
    with pytest.raises(ValueError, match="distinct names"):
        Phases(GRIP, (pick, Phase("pick", ("cubeB",), ("cubeB",), holding=True)))
    with pytest.raises(ValueError, match="unknown keypoint group 'cube'"):
        PolicyLayout(
            K, 3, 10, GROUPS, ROLES, rotation=True, phases=Phases(GRIP, (Phase("all", ("cube",), ("cubeA",)),))
        )
    with pytest.raises(ValueError, match="grip's keypoints"):
        PolicyLayout(
            4, 3, 10, phases=Phases(Grip((2, 3), (7,), (0,), 0.07, 0.01, 0.02), (Phase("all", ("all",), ("all",)),))
        )
    with pytest.raises(ValueError, match="empty_below < closed_below"):
        Grip((17, 18), CUBE_A, CUBE_A, closed_below=0.01, empty_below=0.02, reach=0.02)


def test_segments_need_declared_phases_and_sources_in_every_phase(model, index):
    bare = PolicyLayout(K, 3, 10, GROUPS, ROLES, rotation=True)
    with pytest.raises(ValueError, match="declares none"):
        TransportedKCFMPolicy(model, index, ILWRMap, steps=2, execute=H, layout=bare, segments=True)
    picks = np.flatnonzero(PHASES.index(index.keypoints) == 0)
    only_picks = SourceIndex(index.keypoints[picks], index.chunks[picks])
    with pytest.raises(ValueError, match="in phase 'place'"):
        TransportedKCFMPolicy(model, only_picks, ILWRMap, steps=2, execute=H, layout=LAYOUT, segments=True)


def test_a_configuration_after_its_episodes_first_hold_is_in_the_held_phase(index, tmp_path):
    """Two episodes: open jaws, a hold, then the jaws open again (the release and retreat that end a place). Read
    frame by frame the release looks like a pick; with the index's episodes it belongs to the place it ends, so a
    policy about to pick never follows a demonstration that has already let go. The episodes survive save and load,
    and an index saved without them loads without them."""
    free, held = index.keypoints[0], index.keypoints[1]
    keypoints = np.stack([free, free, held, held, free, free, held, free])
    chunks = index.chunks[:8]
    plain = SourceIndex(keypoints, chunks)
    np.testing.assert_array_equal(source_phases(plain, PHASES), [0, 0, 1, 1, 0, 0, 1, 0])
    episodes = SourceIndex(keypoints, chunks, episodes=np.array([0, 0, 0, 0, 0, 1, 1, 1]))
    np.testing.assert_array_equal(source_phases(episodes, PHASES), [0, 0, 1, 1, 1, 0, 1, 1])
    again = SourceIndex.load(episodes.save(tmp_path / "with.npz"))
    np.testing.assert_array_equal(again.episodes, episodes.episodes)
    assert SourceIndex.load(plain.save(tmp_path / "without.npz")).episodes is None
    with pytest.raises(ValueError, match="one integer per source"):
        SourceIndex(keypoints, chunks, episodes=np.zeros(3, np.int64))


def _residual(phi, source: np.ndarray, target: np.ndarray, rows) -> float:
    """How far ``phi`` leaves the source's keypoints ``rows`` from the target's (m)."""
    with torch.no_grad():
        moved = phi(torch.from_numpy(np.asarray(source, np.float64)[list(rows)])).numpy()
    return float(np.abs(moved - target[list(rows)]).max())


def _fitted_exactly_on(phi, source: np.ndarray, target: np.ndarray, rows) -> bool:
    return _residual(phi, source, target, rows) < 1e-6


def test_before_the_grasp_the_map_follows_the_object_to_pick_alone(model, index):
    """Cube A turned and moved, cube B moved far away on its own: the map is fitted on cube A's keypoints (it carries
    them exactly, not cube B's), the source is a pick configuration, and where cube B stands changes nothing."""
    policy = _policy(model, index)
    source = index.keypoints[4].astype(np.float64)  # an even row: a pick configuration
    rot, shift = _yaw(0.8), np.array([0.1, -0.15, 0.0])
    scene = source @ rot.T + shift
    far_b = scene.copy()
    far_b[list(CUBE_B)] = _cube([-0.1, 0.35, 0.82], 1.1)
    actions = []
    for obs in (scene, far_b):
        policy.reset(3)
        actions.append(policy.act({"keypoints": obs}))
        assert policy.last_phase == "pick" and policy.last_source == 4
        assert _fitted_exactly_on(policy.last_map, source, obs, CUBE_A)
    assert _residual(policy.last_map, source, far_b, CUBE_B) > 0.2
    np.testing.assert_allclose(actions[1], actions[0], atol=1e-9)
    # the K-CFM saw the source scene with the gripper pulled back to where it is relative to cube A
    np.testing.assert_allclose(policy.last_pullback[list(GRIPPER)], source[list(GRIPPER)], atol=1e-9)


def test_after_the_grasp_the_map_follows_the_target_and_the_held_object_is_carried(model, index):
    """Jaws closed on cube A above cube B, the whole scene moved rigidly, then cube B alone moved: the map is fitted
    on cube B's keypoints, the source is a place configuration, and the held cube is pulled back with the gripper."""
    policy = _policy(model, index)
    source = index.keypoints[7].astype(np.float64)  # an odd row: a place configuration
    scene = source @ _yaw(-0.6).T + [0.05, 0.2, 0.0]
    policy.reset(1)
    policy.act({"keypoints": scene})
    assert policy.last_phase == "place" and policy.last_source == 7
    assert _fitted_exactly_on(policy.last_map, source, scene, CUBE_B)
    np.testing.assert_allclose(policy.last_pullback, source, atol=1e-6)  # a rigidly moved source: pulled back onto it
    moved_b = scene.copy()
    moved_b[list(CUBE_B)] += [0.3, -0.1, 0.0]
    policy.act({"keypoints": moved_b})
    assert policy.last_phase == "place" and _fitted_exactly_on(
        policy.last_map, policy.index.keypoints[policy.last_source], moved_b, CUBE_B
    )
    with torch.no_grad():
        held = policy.last_map.inverse(torch.from_numpy(moved_b[list(CUBE_A)])).numpy()
    np.testing.assert_allclose(
        policy.last_pullback[list(CUBE_A)], held, atol=1e-9
    )  # carried: pulled back, not the source's
    assert policy.transports[1].members.tolist() == list(
        range(1, 60, 2)
    )  # place sources are searched among place ones only


def test_without_segments_one_map_is_fitted_on_every_object(model, index):
    policy = _policy(model, index, segments=False)
    source = index.keypoints[7].astype(np.float64)
    scene = source.copy()
    scene[list(CUBE_B)] += [0.3, -0.1, 0.0]
    policy.act({"keypoints": scene})
    assert policy.last_phase is None  # ILWR's fit on both cubes, near each (it interpolates only approximately)
    assert _residual(policy.last_map, policy.index.keypoints[policy.last_source], scene, CUBE_A + CUBE_B) < 0.01


def _symmetric_layout() -> PolicyLayout:
    """:data:`LAYOUT` with cube B's quarter turns and the jaws' half turn (pads swapped, tool turned by pi)."""
    sym = []
    for turn in (1, 2, 3):
        local = turn_permutation(_cube(np.zeros(3), 0.0), np.zeros(3), turn * np.pi / 2)
        perm = list(range(K))
        for i, j in enumerate(local):
            perm[CUBE_B[i]] = CUBE_B[j]
        sym.append(Symmetry(f"cubeB turned {turn}/4", tuple(perm)))
    perm = list(range(K))
    perm[17], perm[18] = 18, 17
    sym.append(Symmetry("jaws turned 1/2", tuple(perm), tool_turn=np.pi, holding=False))
    return PolicyLayout(K, 3, 10, GROUPS, ROLES, rotation=True, phases=PHASES, symmetries=tuple(sym))


def test_a_turn_relabels_a_squares_corners_and_each_phase_admits_the_symmetries_of_what_it_is_fitted_on():
    square = np.array([[1.0, 1.0, 0.0], [-1.0, 1.0, 0.0], [-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 0.0, 2.0]])
    assert turn_permutation(square, np.zeros(3), np.pi / 2) == (
        1,
        2,
        3,
        0,
        4,
    )  # corner i turns onto corner i + 1; the axis stays
    assert turn_permutation(square + 5.0, np.full(3, 5.0), np.pi) == (2, 3, 0, 1, 4)
    with pytest.raises(ValueError, match="does not map these 5 keypoints onto themselves"):
        turn_permutation(square, np.zeros(3), 0.3)
    with pytest.raises(ValueError, match="must be a permutation"):
        Symmetry("bad", (0, 0, 1))
    layout = _symmetric_layout()
    pick = [s.name for s in phase_correspondences(layout.symmetries, K, CUBE_A, holding=False)]
    place = [s.name for s in phase_correspondences(layout.symmetries, K, CUBE_B, holding=True)]
    assert pick == [
        "identity",
        "jaws turned 1/2",
    ]  # cube B's turns do not touch the pick's map; the jaws turn while empty
    assert place == [
        "identity",
        "cubeB turned 1/4",
        "cubeB turned 2/4",
        "cubeB turned 3/4",
    ]  # not the jaws: they hold cube A
    with pytest.raises(ValueError, match="relabels 19 keypoints; the layout has 20"):
        PolicyLayout(20, 3, 10, symmetries=layout.symmetries)


def test_a_chunk_the_arm_cannot_follow_is_replaced_by_the_symmetric_correspondence_it_can(model, index):
    """The Panda's wrist near its stop: the identity's chunk would take it past (the arm's cost is inf) and is never
    sent; the jaws' half turn gives a chunk it can follow, which is sent and kept at the next decision. With no
    candidate in reach, the first is sent and the decision counted."""
    layout = _symmetric_layout()
    arm = SuiteArmLimits(pads=(17, 18), base_xy=(-0.3, 0.0))  # every chunk in reach: the wrist decides
    policy = TransportedKCFMPolicy(model, index, ILWRMap, steps=2, execute=H, layout=layout, segments=True, arm=arm)
    scene = index.keypoints[4].astype(np.float64) @ _yaw(0.8).T + [0.1, -0.15, 0.0]  # a pick configuration, turned
    pick = policy.transports[0]
    policy.reset(3)
    chunks = [
        policy._transported(pick, 4, c, [scene])[0] for c in pick.correspondences
    ]  # the draws act() makes, in order
    pads = scene[17] - scene[18]
    now = np.arctan2(pads[1], pads[0]) + np.pi  # the jaws' yaw
    turns = [np.sum(wrap_angle(np.diff([now, *(yaw_of(r) for r in rot6d_to_matrix(c[:, 3:9]))]))) for c in chunks]
    assert 2.0 < abs(turns[1] - turns[0]) < 4.3  # the half turn's chunk turns the jaws about the other way round
    wrist = turns[0] + 2.8 * np.sign(
        turns[1] - turns[0]
    )  # the identity's turn takes the last joint 2.8 rad away: past its stop
    obs = {"keypoints": scene, "joints": np.r_[np.zeros(6), wrist]}
    assert arm.cost(obs, chunks[0]) == np.inf and np.isfinite(arm.cost(obs, chunks[1]))
    policy.reset(3)
    sent = policy.act(obs)
    assert policy.last_correspondence.name == "jaws turned 1/2" and policy.last_source == 4 and policy.unfollowable == 0
    np.testing.assert_allclose(sent, chunks[1], atol=1e-12)
    np.testing.assert_allclose(
        policy.last_pullback[[17, 18]], index.keypoints[4][[18, 17]], atol=1e-6
    )  # the pads, relabelled
    policy.act(obs)
    assert policy.last_correspondence.name == "jaws turned 1/2" and policy.kept == {
        0: 1
    }  # kept while it can be followed
    far = TransportedKCFMPolicy(
        model,
        index,
        ILWRMap,
        steps=2,
        execute=H,
        layout=layout,
        segments=True,
        arm=SuiteArmLimits((17, 18), reach=0.01),
    )
    far.reset(3)
    np.testing.assert_allclose(
        far.act(obs), chunks[0], atol=1e-12
    )  # nothing within 1 cm of the base: the first, counted
    assert far.unfollowable == 1 and far.last_correspondence.name == "identity"


class _RefusesFirst:
    """An arm that cannot follow the first ``n`` chunks it is shown (one source's every correspondence)."""

    def __init__(self, n: int):
        self.n, self.seen = n, 0

    def cost(self, obs, chunk):
        self.seen += 1
        return np.inf if self.seen <= self.n else 0.0


def test_when_no_correspondence_of_the_chosen_source_can_be_followed_the_next_nearest_source_is_tried(model, index):
    layout = _symmetric_layout()
    policy = TransportedKCFMPolicy(
        model, index, ILWRMap, steps=2, execute=H, layout=layout, segments=True, arm=_RefusesFirst(2)
    )
    scene = index.keypoints[4].astype(np.float64)
    policy.act({"keypoints": scene})
    near, _ = policy.transports[0].choice.index.query_k(scene, 2)
    assert policy.last_source == int(policy.transports[0].members[near[1]]) != 4 and policy.unfollowable == 0
    with pytest.raises(ValueError, match="arm must have cost"):
        TransportedKCFMPolicy(model, index, ILWRMap, steps=2, execute=H, layout=layout, segments=True, arm=object())


@pytest.mark.slow
def test_in_robosuites_stack_the_phase_switches_at_the_grasp_and_back_at_the_release():
    """The scripted Stack demonstration in a d0 scene: the phase read from the keypoints a policy observes is ``pick``
    until the jaws have closed on cube A (after the close is commanded, before the lift ends), ``place`` while it is
    carried, and ``pick`` again once the jaws open over cube B; the simulator's own grasp check agrees at both ends."""
    from kpflow.geometry.angles import yaw_of
    from kpflow.tasks.suite.demonstrator import plan_segment
    from kpflow.tasks.suite.task import SuiteTask

    task = SuiteTask("stack")
    env = task.make_sim()
    env.reset_to(task.sample_scene(env, "d0", 0))
    home_yaw = yaw_of(env.home_pose[1])
    phases, grasps, grasping = [], [], []
    for name in task.spec.segments:
        trajectory = plan_segment(env, task.spec, name, home_yaw)
        run = task.run_segment(env, trajectory)
        assert run.failure is None
        phases += [p.name for p in map(task.policy_layout.phases.of, run.keypoints)]
        grasps.append(trajectory.grasp)
        grasping.append(env.grasping(task.spec.grasp))
    pick_steps = len(grasps[0])
    switches = [t for t in range(1, len(phases)) if phases[t] != phases[t - 1]]
    assert phases[0] == "pick" and len(switches) == 2, switches
    close_commanded = int(np.argmax(grasps[0]))
    assert close_commanded < switches[0] < pick_steps  # held once the jaws have closed, during the pick segment
    assert phases[pick_steps] == "place" and grasping[0]  # the simulator agrees: cube A is held when the pick ends
    open_commanded = pick_steps + int(np.argmin(grasps[1]))
    assert open_commanded < switches[1] and phases[-1] == "pick" and not grasping[1]
