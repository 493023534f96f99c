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

from kpflow.data.source_index import SourceIndex
from kpflow.geometry.rotations import matrix_to_rot6d
from kpflow.maps import ILWRMap
from kpflow.policies.base import PolicyLayout
from kpflow.policies.kcfm.model import KCFM
from kpflow.policies.phases import Grip, Phase, Phases
from kpflow.policies.transported_kcfm import TransportedKCFMPolicy, source_phases
from tests.helpers import cube_corners as _cube
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
    chunk = np.concatenate([path, np.repeat(matrix_to_rot6d(jaws)[None], H, 0), np.full((H, 1), 1.0 if holding else -1.0)], 1)
    return keypoints, chunk


@pytest.fixture(scope="module")
def index() -> SourceIndex:
    rng = np.random.default_rng(0)
    scenes = [_scene(rng, holding=i % 2 == 1) for i in range(60)]
    return SourceIndex(np.stack([s[0] for s in scenes]), np.stack([s[1] for s in scenes]), LAYOUT.weights({"robot": 4.0}), CUBE_A)


@pytest.fixture(scope="module")
def model(index) -> KCFM:
    """A 3-D K-CFM with random weights and the data's normalisation."""
    torch.manual_seed(0)
    model = KCFM(horizon=H, n_obs=1, n_keypoints=K, keypoint_dim=3, action_dim=10, down_dims=(16, 32)).eval()
    model.set_normalisation(index.keypoints, index.chunks[:, 0])
    return model


def _policy(model, index, segments: bool = True) -> TransportedKCFMPolicy:
    return TransportedKCFMPolicy(model, index, ILWRMap, steps=2, execute=H, layout=LAYOUT, segments=segments,
                                 fit_on=None if segments else LAYOUT.indices("objects", "goals"))  # fmt: skip


def test_a_grip_on_a_segment_holds_anywhere_along_it():
    """A handle from (0, 0, 0) to (0.05, 0, 0): jaws closed at either end or between hold it; beyond its end, or 3 cm
    to its side, they do not (closed form: the distance to the segment)."""
    grip = Grip((1, 2), (3,), (4,), closed_below=0.07, empty_below=0.01, reach=0.02)
    handle = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]])
    cases = {(0.0, 0.0): True, (0.05, 0.0): True, (0.025, 0.0): True, (0.065, 0.0): True, (0.075, 0.0): False, (0.025, 0.03): False}
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
        PolicyLayout(K, 3, 10, GROUPS, ROLES, rotation=True, phases=Phases(GRIP, (Phase("all", ("cube",), ("cubeA",)),)))
    with pytest.raises(ValueError, match="grip's keypoints"):
        PolicyLayout(4, 3, 10, phases=Phases(Grip((2, 3), (7,), (0,), 0.07, 0.01, 0.02), (Phase("all", ("all",), ("all",)),)))
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
    assert policy.last_phase == "place" and _fitted_exactly_on(policy.last_map, policy.index.keypoints[policy.last_source], moved_b, CUBE_B)
    with torch.no_grad():
        held = policy.last_map.inverse(torch.from_numpy(moved_b[list(CUBE_A)])).numpy()
    np.testing.assert_allclose(policy.last_pullback[list(CUBE_A)], held, atol=1e-9)  # carried: pulled back, not the source's
    assert policy.transports[1].members.tolist() == list(range(1, 60, 2))  # place sources are searched among place ones only


def test_without_segments_one_map_is_fitted_on_every_object(model, index):
    policy = _policy(model, index, segments=False)
    source = index.keypoints[7].astype(np.float64)
    scene = source.copy()
    scene[list(CUBE_B)] += [0.3, -0.1, 0.0]
    policy.act({"keypoints": scene})
    assert policy.last_phase is None  # ILWR's fit on both cubes, near each (it interpolates only approximately)
    assert _residual(policy.last_map, policy.index.keypoints[policy.last_source], scene, CUBE_A + CUBE_B) < 0.01


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
