"""Stacking with keypoints from images (real MuJoCo, rendering headless): scenes, the environment's ground truth,
lifting against it, the scripted demonstration, transport through exact and image-found pairs, and the CLI."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from scipy.spatial.transform import Rotation

from kpflow.core.task import Demonstration
from kpflow.eval.demo_transport_trial import DemoTransportTrial
from kpflow.eval.reports.stacking import StackingReport, grasp_errors
from kpflow.eval.stats import wilson_interval
from kpflow.maps import GPMap
from kpflow.tasks.arm.motion import pointing_down
from kpflow.tasks.stacking.demonstrator import execute, nearest_half_turn
from kpflow.tasks.stacking.keypoints import BACKGROUND, Matcher, labels_at, lift, true_targets
from kpflow.tasks.stacking.objects import CHEESE, LETTUCE, SIZES
from kpflow.tasks.stacking.scene import AREA_X, SIDE_Y, SOURCE_SCENE, YAW_RANGE, Scene, sample_scene
from kpflow.tasks.stacking.task import StackingTask, StackingView
from kpflow.trajectory import Trajectory
from kpflow.vision import SiftBackbone, project_points
from tests.helpers import run_command

ROOT = Path(__file__).resolve().parents[1]


TASK = StackingTask(camera_size=(480, 480))


@pytest.fixture(scope="module")
def env():
    torch.set_num_threads(1)
    return TASK.make_env()


@pytest.fixture(scope="module")
def source(env):
    return TASK.demonstrate(env)


def trial(env, source, scene, keypoint_source, task=TASK):
    """One trial with the GP map in ``scene``."""
    runner = DemoTransportTrial(task, StackingReport(), {"gp": GPMap}, oracle=True)
    runner.env, runner.source = env, source  # the module's simulator and recording (what setup() would build)
    return runner.run_scene(scene, keypoint_source, GPMap)


def test_scenes_are_seeded_and_keep_or_swap_the_sides():
    moved = [sample_scene("moved", i) for i in range(30)]
    swapped = [sample_scene("swapped", i) for i in range(30)]
    assert sample_scene("moved", 4) == moved[4] and sample_scene("moved", 4, seed=1) != moved[4]
    for scenes, (cheese_side, lettuce_side) in ((moved, ("right", "left")), (swapped, ("left", "right"))):
        for s in scenes:
            placed = (
                (s.cheese_pose, cheese_side, SOURCE_SCENE.cheese_pose),
                (s.lettuce_pose, lettuce_side, SOURCE_SCENE.lettuce_pose),
            )
            for pose, side, demo in placed:
                assert AREA_X[0] <= pose[0] <= AREA_X[1] and SIDE_Y[side][0] <= pose[1] <= SIDE_Y[side][1]
                assert abs(pose[2] - demo[2]) <= YAW_RANGE
    with pytest.raises(ValueError, match="overlap"):
        Scene((0.0, 0.0, 0.0), (0.05, 0.0, 0.0))
    with pytest.raises(ValueError, match="cheese_pose"):
        Scene((0.0, float("nan"), 0.0), (0.0, 0.3, 0.0))
    with pytest.raises(ValueError, match="condition"):
        sample_scene("full", 0)


@pytest.mark.slow
def test_env_puts_the_blocks_where_the_scene_says(env):
    scene = sample_scene("swapped", 2)
    env.reset_to(scene)
    for name, (x, y, yaw) in ((CHEESE, scene.cheese_pose), (LETTUCE, scene.lettuce_pose)):
        centre, rot, half = env.object_box(name)
        assert np.allclose(centre[:2], (x, y), atol=2e-3) and np.allclose(half, SIZES[name])
        assert abs(centre[2] - half[2] - env.table_top) < 2e-3  # resting on the table
        assert abs(nearest_half_turn(np.arctan2(rot[1, 0], rot[0, 0]), yaw) - yaw) < 1e-2
    assert not env.stacked() and not env.holding()
    image = env.render_topdown()
    assert image["rgb"].shape == (480, 480, 3) and image["depth"].shape == (480, 480)
    assert all(image["masks"][name].sum() > 500 for name in (CHEESE, LETTUCE))


@pytest.mark.slow
def test_lifted_pixels_land_on_the_simulators_blocks(env):
    env.reset_to(sample_scene("moved", 1))
    image = env.render_topdown()
    for name in (CHEESE, LETTUCE):
        centre, rot, half = env.object_box(name)
        corners = centre + (np.array([[0.0, 0.0, 1.0], [0.8, 0.8, 1.0], [-0.8, 0.5, 1.0]]) * half) @ rot.T
        pixels = project_points(corners, image["intrinsics"], image["camera_to_world"])[0].numpy()
        assert labels_at(image, pixels) == [name] * 3
        # a pixel is about 1.5 mm on the table: the lifted point is within a few mm of the true one
        assert np.abs(lift(image, pixels) - corners).max() < 4e-3
    assert labels_at(image, np.array([[2.0, 2.0]])) == [BACKGROUND]


def test_true_targets_move_block_points_rigidly_and_keep_the_rest():
    rot = Rotation.from_euler("z", 0.7).as_matrix()
    before = {CHEESE: (np.array([0.1, 0.0, 0.8]), np.eye(3))}
    now = {CHEESE: (np.array([-0.2, 0.3, 0.8]), rot)}
    points = np.array([[0.1, 0.0, 0.82], [0.13, 0.01, 0.82], [0.4, 0.4, 0.8]])
    moved = true_targets(points, [CHEESE, CHEESE, BACKGROUND], before, now)
    assert np.allclose(moved[0], [-0.2, 0.3, 0.82])
    assert np.allclose(moved[1], [-0.2, 0.3, 0.8] + rot @ [0.03, 0.01, 0.02])
    assert np.allclose(moved[2], points[2])


def test_half_turns_and_grasp_errors_in_closed_form():
    assert nearest_half_turn(3.0, 0.0) == pytest.approx(3.0 - np.pi)
    assert nearest_half_turn(-0.2, 0.1) == pytest.approx(-0.2)
    assert nearest_half_turn(np.pi / 2, 0.0) == pytest.approx(-np.pi / 2)  # the boundary: [ref - pi/2, ref + pi/2)
    turn = Rotation.from_euler("z", 0.5).as_matrix()

    def path(positions, rotations):
        return Trajectory(
            np.array(positions, float), np.stack(rotations), np.array([False, True]), np.array(["approach", "seal"])
        )

    view = StackingView(
        image={}, poses={CHEESE: (np.array([0.1, -0.2, 0.82]), np.eye(3))}, boxes={}, start_box=np.zeros((8, 3))
    )
    source = Demonstration(
        None, view, path([[0.0, 0.0, 1.0], [0.1, -0.2, 0.84]], [pointing_down(0.0), pointing_down(0.0)]), None
    )
    now = {CHEESE: (np.array([-0.1, 0.1, 0.82]), turn)}
    ideal = path([[0.0, 0.0, 1.0], [-0.1, 0.1, 0.84]], [np.eye(3), pointing_down(0.5)])
    assert grasp_errors(source, ideal, now) == pytest.approx((0.0, 0.0), abs=1e-9)
    flipped = dataclasses.replace(
        ideal, rotations=np.stack([np.eye(3), pointing_down(0.5 + np.pi)])
    )  # a box grasped turned by pi
    assert grasp_errors(source, flipped, now)[0] == pytest.approx(0.0, abs=1e-6)
    off = path(ideal.positions + [0.0, 0.003, 0.004], [np.eye(3), pointing_down(0.6)])
    assert grasp_errors(source, off, now) == pytest.approx((np.rad2deg(0.1), 5.0))


@pytest.mark.slow
def test_scripted_demonstration_stacks_the_cheese(source, env):
    assert source.execution.success and source.execution.failure is None
    assert source.execution.grasped == CHEESE
    assert set(source.trajectory.phases) >= {"approach", "seal", "carry", "release"}


@pytest.mark.slow
def test_identical_scene_with_exact_pairs_reproduces_the_demonstration(env, source):
    r = trial(env, source, SOURCE_SCENE, "oracle")
    assert r.success and r.scores["grasp_error_deg"] < 1.0 and r.scores["grasp_error_mm"] < 1.0
    assert np.allclose(r.artefacts["trajectory"].positions, source.trajectory.positions, atol=2e-3)


@pytest.mark.slow
def test_a_stacking_trial_end_to_end_with_image_correspondences(env, source):
    task = StackingTask(camera_size=(480, 480), matcher=Matcher(consistency={"radius": 0.12, "tolerance": 0.015}))
    r = trial(env, source, sample_scene("moved", 0), SiftBackbone(colour_weight=2.0), task=task)
    pairs, s = r.artefacts["view"].pairs, r.scores
    assert (
        s["n_pairs"] + s["rejected"] == 7 and s["pairs_on"][CHEESE] >= 1 and sum(s["pairs_on"].values()) == s["n_pairs"]
    )
    assert pairs.pixels_before.shape == pairs.pixels_now.shape == (7, 2)
    assert pairs.source.shape == pairs.target.shape == (7, 3)
    assert s["pair_error_mm"] < 15.0
    assert r.success, r.failure
    # one pair on the cheese fixes where it is but not how it turned: the grasp's yaw is only roughly right
    assert s["grasp_error_mm"] < 20.0 and s["grasp_error_deg"] < 45.0


@pytest.mark.slow
def test_execute_reports_why_a_trial_failed(env, source):
    env.reset_to(sample_scene("moved", 3))  # the cheese is elsewhere: the untransported demonstration misses it
    result = execute(env, source.trajectory)
    assert not result.success and result.failure == "not grasped"
    with pytest.raises(ValueError, match="NaN"):
        dataclasses.replace(source.trajectory, positions=np.full_like(source.trajectory.positions, np.nan))
    with pytest.raises(ValueError, match="oracle"):
        trial(env, source, SOURCE_SCENE, "orcale")


@pytest.mark.slow
def test_evaluate_stacking_cli_writes_table_matches_and_config(tmp_path):
    cmd = [
        "experiment=stacking", "experiment.n_trials=1", "workers=1", "logger=none",
        "experiment.conditions=[moved]", "~experiment.trial.backbones.sift", "~experiment.trial.maps.gp_translation",
        "experiment.trial.report.examples=1", "experiment.videos=0", f"hydra.run.dir={tmp_path}",
    ]  # fmt: skip
    done = run_command("kpflow.cli.evaluate", *cmd)  # in this process: what kpflow-evaluate runs, without re-importing
    assert done.returncode == 0, done.stderr[-3000:]
    cfg = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert cfg["experiment"]["n_trials"] == 1 and cfg["task"]["source"]["cheese_pose"] == list(SOURCE_SCENE.cheese_pose)
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["source"]["success"]
    assert {(s["keypoints"], s["map"]) for s in results["summary"]} == {
        ("sift_colour", "gp"),
        ("vit_random", "gp"),
        ("oracle", "gp"),
    }
    reasons = {
        None,
        "not grasped",
        "unreachable",
        "near-singular",
        "grasped the lettuce",
        "missed the lettuce",
        "no correspondences",
    }
    assert all((t["failure"] is None) == t["success"] and t["failure"] in reasons for t in results["trials"])
    assert all(len(t["pair_errors_mm"]) == t["n_pairs"] for t in results["trials"])
    lo, hi = wilson_interval(1, 1)
    assert (
        f"| moved | oracle | gp | 1/1 = 100% [{100 * lo:.0f}, {100 * hi:.0f}] |"
        in (tmp_path / "results.md").read_text()
    )
    assert len(list(tmp_path.glob("matches_moved_*.png"))) == 3
