"""Keypoints from cameras (issue 44): frames lift to the known points, boxes of known point clouds come back, the
noise model is seeded and has the configured statistics, and a rendered robosuite cube's box keypoints match the
simulator's within what the pixels allow."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kpflow.vision.boxes import fit_footprint_box, largest_cluster, voxel_centres
from kpflow.vision.cameras import CameraFrame
from kpflow.vision.depth_filter import smooth_depth
from kpflow.vision.noise import CameraNoise
from kpflow.vision.segmentation import InstanceSegmenter, Segmenter

H, W, F = 48, 64, 50.0
K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])


def looking_down(height: float) -> np.ndarray:
    """A camera ``height`` m above the origin looking straight down (OpenCV axes: x right = world x, y down = world
    -y, z forward = world -z)."""
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
    pose[2, 3] = height
    return pose


def frame(depth: np.ndarray, pose: np.ndarray = None, segmentation=None) -> CameraFrame:
    return CameraFrame(
        "test",
        np.zeros((*depth.shape, 3), np.uint8),
        depth,
        K,
        looking_down(2.0) if pose is None else pose,
        segmentation,
    )


# ------------------------------------------------------------------------------------------- lifting a frame


def test_a_flat_depth_image_lifts_to_the_floor_below_the_camera():
    """Depth 2 m everywhere from 2 m up: every pixel lands on z = 0, pixel (v, u) at x = (u + 0.5 - W/2) 2 / F,
    y = -(v + 0.5 - H/2) 2 / F; holes lift to nothing."""
    depth = np.full((H, W), 2.0)
    depth[0, 0], depth[1, 1] = 0.0, np.nan
    points = frame(depth).points()
    assert points.shape == (H * W - 2, 3)
    np.testing.assert_allclose(points[:, 2], 0.0, atol=1e-12)
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    np.testing.assert_allclose(points[:, 0], (u + 0.5 - W / 2) * 2.0 / F, atol=1e-12)
    np.testing.assert_allclose(points[:, 1], -(v + 0.5 - H / 2) * 2.0 / F, atol=1e-12)
    mask = np.zeros((H, W), bool)
    mask[10:12, 20:23] = True
    assert frame(depth).points(mask).shape == (6, 3)


def test_frames_refuse_what_does_not_fit():
    with pytest.raises(ValueError, match="rgb must be"):
        CameraFrame("c", np.zeros((H, W + 1, 3)), np.ones((H, W)), K, np.eye(4))
    with pytest.raises(ValueError, match="segmentation must be"):
        CameraFrame("c", np.zeros((H, W, 3)), np.ones((H, W)), K, np.eye(4), np.zeros((H, 1)))
    with pytest.raises(ValueError, match="mask must be"):
        frame(np.ones((H, W))).points(np.ones((H, 2), bool))
    with pytest.raises(ValueError, match="gives no segmentation"):
        frame(np.ones((H, W))).mask_of([1])


def test_instance_segmenter_reads_named_ids():
    seg = np.full((H, W), -1)
    seg[5:10, 5:10], seg[20:30, 40:50] = 3, 7
    f = frame(np.ones((H, W)), segmentation=seg)
    segmenter = InstanceSegmenter({"cube": [3], "bin": [7, 8]})
    assert isinstance(segmenter, Segmenter)
    cube, bin_ = segmenter.masks(f, ["cube", "bin"])
    assert cube.sum() == 25 and bin_.sum() == 100 and not (cube & bin_).any()
    with pytest.raises(ValueError, match=r"no instance ids for \['peg'\]"):
        segmenter.masks(f, ["peg"])


# ------------------------------------------------------------------------------------------- boxes


def box_surface(centre, yaw, half, n=4000, seed=0) -> np.ndarray:
    """Points on the top and the four sides of a box standing on z = 0 (``half``: x, y, z half sides)."""
    rng = np.random.default_rng(seed)
    local = rng.uniform(-1, 1, (n, 3)) * half
    face = rng.integers(0, 5, n)
    local[face == 0, 2] = half[2]  # top
    for f, (axis, sign) in enumerate(((0, 1), (0, -1), (1, 1), (1, -1)), start=1):
        local[face == f, axis] = sign * half[axis]
    local[:, 2] += half[2]
    return local @ Rotation.from_euler("z", yaw).as_matrix().T + np.r_[centre, 0.0]


@pytest.mark.parametrize("yaw", [0.3, -1.2, 1.5707])
def test_the_footprint_box_of_a_box_is_the_box(yaw):
    half = np.array([0.06, 0.025, 0.02])
    box = fit_footprint_box(box_surface([0.1, -0.2], yaw, half), voxel=0.002)
    np.testing.assert_allclose(box.centre, [0.1, -0.2], atol=2e-3)
    np.testing.assert_allclose(box.half, half[:2], atol=2e-3)
    assert box.top == pytest.approx(0.04, abs=1.5e-3)
    turn = (box.yaw - yaw + np.pi / 2) % np.pi - np.pi / 2  # a rectangle's axis is defined up to a half turn
    assert abs(turn) < np.radians(2)
    assert -np.pi / 2 < box.yaw <= np.pi / 2


def test_stray_points_are_left_out_and_unseen_objects_refused():
    points = box_surface([0.0, 0.0], 0.0, np.array([0.02, 0.02, 0.02]))
    stray = np.array([[0.5, 0.5, 0.0], [0.52, 0.5, 0.0], [-0.4, 0.1, 0.3]])
    box = fit_footprint_box(np.concatenate([points, stray]))
    np.testing.assert_allclose(box.half, [0.02, 0.02], atol=2e-3)
    assert len(largest_cluster(np.concatenate([points, stray]), 0.01)) == len(points)
    with pytest.raises(ValueError, match="seen in 1 voxels"):
        fit_footprint_box(stray[:2])
    with pytest.raises(ValueError, match="finite"):
        fit_footprint_box(np.full((5, 3), np.nan))


def test_voxel_centres_are_the_means_of_their_cells():
    points = np.array([[0.001, 0.001, 0.001], [0.003, 0.001, 0.001], [0.011, 0.0, 0.0]])
    np.testing.assert_allclose(voxel_centres(points, 0.01), [[0.002, 0.001, 0.001], [0.011, 0.0, 0.0]])


# ------------------------------------------------------------------------------------------- depth filter, noise


def test_smoothing_within_a_mask_cuts_the_noise_and_touches_nothing_else():
    rng = np.random.default_rng(0)
    depth = 1.0 + 0.01 * rng.standard_normal((H, W))
    depth[5, 5] = 0.0
    mask = np.zeros((H, W), bool)
    mask[10:40, 10:50] = True
    out = smooth_depth(depth, mask, 5)
    inner = np.zeros_like(mask)
    inner[12:38, 12:48] = True  # full windows: the mean of 25 pixels
    assert np.std(out[inner]) < 0.01 / 5 * 1.25
    np.testing.assert_array_equal(out[~mask], np.where(depth > 0, depth, 0.0)[~mask])
    assert out[5, 5] == 0.0
    np.testing.assert_array_equal(smooth_depth(depth, mask, 1), np.where(depth > 0, depth, 0.0))
    with pytest.raises(ValueError, match="odd integer"):
        smooth_depth(depth, mask, 4)


def test_noise_is_seeded_and_has_the_configured_statistics():
    noise = CameraNoise()
    depth = np.full((200, 300), 1.5)
    a, b = noise.depth(depth, np.random.default_rng(1)), noise.depth(depth, np.random.default_rng(1))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, noise.depth(depth, np.random.default_rng(2)))
    returned = a > 0
    assert 1 - returned.mean() == pytest.approx(noise.hole_fraction, abs=0.003)  # no edges in a flat image
    np.testing.assert_allclose(a[returned] / noise.depth_unit, np.round(a[returned] / noise.depth_unit), atol=1e-6)
    sigma = noise.depth_std(1.5)
    assert sigma == pytest.approx(1.5**2 * 0.08 / (noise.focal_px * 0.05))
    assert np.std(a[returned] - 1.5) == pytest.approx(np.sqrt(sigma**2 + noise.depth_unit**2 / 12), rel=0.03)
    step = np.full((40, 40), 1.0)
    step[:, 20:] = 1.2  # a 20 cm jump: the pixels beside it become holes
    edged = replace(noise, hole_fraction=0.0).depth(step, np.random.default_rng(0))
    assert (edged[:, 18:22] == 0).all() and (edged[:, :17] > 0).all() and (edged[:, 23:] > 0).all()


def test_pose_error_has_the_configured_size_and_masks_move_by_whole_pixels():
    noise = CameraNoise(pose_deg=3.0, pose_m=0.01)
    pose = looking_down(2.0)
    for seed in range(5):
        moved = noise.pose(pose, np.random.default_rng(seed))
        turn = Rotation.from_matrix(moved[:3, :3] @ pose[:3, :3].T).magnitude()
        assert np.degrees(turn) == pytest.approx(3.0)
        assert np.linalg.norm(moved[:3, 3] - pose[:3, 3]) == pytest.approx(0.01)
    mask = np.zeros((30, 30), bool)
    mask[10:20, 10:20] = True
    sizes = {int(CameraNoise(mask_px=2).mask(mask, np.random.default_rng(s)).sum()) for s in range(40)}
    # eroded by 2 or 1, as it was, dilated by 1 or 2 (scipy's cross-shaped step grows a square's sides, not its corners)
    assert sizes == {6 * 6, 8 * 8, 10 * 10, 10 * 10 + 4 * 10, 10 * 10 + 4 * 10 + 4 * 10 + 4}


def test_a_calibration_stream_keeps_the_pose_error_fixed_across_captures():
    """``frame(..., calibration)``: the pose error comes from the calibration's generator (seeded the same at every
    capture, the same error: one calibration), the depth noise from the frame's stream (new at every capture)."""
    f, noise, rng = frame(np.full((H, W), 2.0)), CameraNoise(), np.random.default_rng(0)
    a, b = (noise.frame(f, rng, np.random.default_rng([7, 1, 0])) for _ in range(2))
    np.testing.assert_array_equal(a.cam_to_world, b.cam_to_world)
    assert not np.array_equal(a.depth, b.depth) and not np.array_equal(a.cam_to_world, f.cam_to_world)


def test_temporal_mean_averages_returns_and_keeps_holes():
    from kpflow.vision.depth_filter import temporal_mean

    a, b = np.full((2, 3), 1.0), np.full((2, 3), 3.0)
    b[0, 0], a[1, 1], b[1, 1] = 0.0, np.nan, -1.0
    out = temporal_mean([a, b])
    np.testing.assert_array_equal(out, [[1.0, 2.0, 2.0], [2.0, 0.0, 2.0]])  # one return: itself; none: a hole
    rng = np.random.default_rng(0)
    noisy = [1.0 + 0.01 * rng.standard_normal((50, 50)) for _ in range(16)]
    assert np.std(temporal_mean(noisy)) == pytest.approx(0.01 / 4, rel=0.1)  # sqrt(16)
    with pytest.raises(ValueError, match="depths must be \\[N, H, W\\]"):
        temporal_mean(np.zeros((3, 3)))


def test_no_noise_changes_nothing():
    f = frame(np.full((H, W), 2.0))
    rng = np.random.default_rng(0)
    quiet = CameraNoise.off()
    g = quiet.frame(f, rng)
    np.testing.assert_array_equal(g.depth, f.depth)
    np.testing.assert_array_equal(g.cam_to_world, f.cam_to_world)
    mask = np.eye(H, W, dtype=bool)
    np.testing.assert_array_equal(quiet.mask(mask, rng), mask)
    with pytest.raises(ValueError, match="hole_fraction must be finite and >= 0"):
        CameraNoise(hole_fraction=-0.1)
