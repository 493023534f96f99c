import math

import numpy as np
import pytest
import torch

from kpflow.geometry.rotations import so3_exp, so3_log
from kpflow.tasks.frames import (
    LASA_SHAPES,
    DemonstratedMotion,
    Frame,
    demonstrate,
    frame_keypoints,
    lasa_frames,
    load_lasa,
    random_frame,
    scene_keypoints,
)
from kpflow.tasks.frames.task import LASA_MOVES, FramesTask


def _angle_between(u, v):
    u, v = u.double(), v.double()
    return math.degrees(torch.arccos((u @ v / (u.norm() * v.norm())).clamp(-1, 1)).item())


def _assert_rotations(R, atol):
    D = R.shape[-1]
    eye = torch.eye(D, dtype=R.dtype)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye.expand_as(R), atol=atol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(R.shape[:-2], dtype=R.dtype), atol=atol, rtol=0)


# ---- frames and keypoints -------------------------------------------------------------


def test_keypoints_2d_layout():
    f = Frame.from_2d(1.0, 2.0, math.pi / 2, dtype=torch.float64)
    kp = frame_keypoints(f, size=0.5)
    # origin, +x, +y, -x, -y in local coordinates; the frame's x axis is world +y.
    expected = torch.tensor([[1.0, 2.0], [1.0, 2.5], [0.5, 2.0], [1.0, 1.5], [1.5, 2.0]], dtype=torch.float64)
    torch.testing.assert_close(kp, expected)


def test_keypoints_3d_layout():
    f = Frame.from_3d([1.0, 0.0, 0.0], torch.eye(3), dtype=torch.float64)
    kp = frame_keypoints(f, size=2.0)
    expected = torch.tensor([[1, 0, 0], [3, 0, 0], [1, 2, 0], [1, 0, 2], [-1, 0, 0]], dtype=torch.float64)
    torch.testing.assert_close(kp, expected)


@pytest.mark.parametrize("dim", [2, 3])
def test_keypoints_follow_rigid_transforms(dim):
    g = torch.Generator().manual_seed(0)
    f = random_frame(g, dim, dtype=torch.float64)
    G = random_frame(g, dim, workspace=3.0, dtype=torch.float64)
    moved = G @ f
    torch.testing.assert_close(frame_keypoints(moved, 0.3), G.transform(frame_keypoints(f, 0.3)))
    # Keypoints sit exactly at the frame pose: local coordinates are the fixed pattern.
    local = f.inverse_transform(frame_keypoints(f, 0.3))
    torch.testing.assert_close(local[0], torch.zeros(dim, dtype=torch.float64))
    torch.testing.assert_close(local[1], 0.3 * torch.eye(dim, dtype=torch.float64)[0])
    # Pairwise distances are invariant (rigidity).
    kp, kq = frame_keypoints(f, 0.3), frame_keypoints(moved, 0.3)
    torch.testing.assert_close(torch.cdist(kp, kp), torch.cdist(kq, kq))


def test_scene_keypoints_concatenate_in_order():
    g = torch.Generator().manual_seed(1)
    frames = [random_frame(g, 3) for _ in range(3)]
    kp = scene_keypoints(frames, size=0.2)
    assert kp.shape == (15, 3)
    for i, f in enumerate(frames):
        torch.testing.assert_close(kp[5 * i : 5 * i + 5], frame_keypoints(f, 0.2))


def test_frame_constructors_and_validation():
    f = Frame.from_euler_3d([0.0, 0.0, 0.0], [0.0, 0.0, math.pi / 2])
    torch.testing.assert_close(f.x_axis, torch.tensor([0.0, 1.0, 0.0]), atol=1e-6, rtol=0)
    f64 = Frame.from_2d(np.float64(1.0), 0.0, 0.3, dtype=torch.float64)
    assert f64.dtype == torch.float64
    torch.testing.assert_close(
        f64.inverse().transform(f64.transform(torch.tensor([0.2, -0.4], dtype=torch.float64))),
        torch.tensor([0.2, -0.4], dtype=torch.float64),
    )
    with pytest.raises(ValueError, match="not orthonormal"):
        Frame(torch.zeros(2), torch.tensor([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="reflection"):
        Frame(torch.zeros(2), torch.diag(torch.tensor([1.0, -1.0])))
    with pytest.raises(ValueError, match="D = 2 or 3"):
        Frame(torch.zeros(4), torch.eye(4))
    with pytest.raises(ValueError, match="NaN"):
        Frame.from_2d(float("nan"), 0.0, 0.0)


def test_random_frame_workspace_and_rotation():
    g = torch.Generator().manual_seed(2)
    for _ in range(20):
        f = random_frame(g, 3, workspace=([0.0, 0.0, 0.5], [1.0, 1.0, 1.0]))
        assert (f.position >= torch.tensor([0.0, 0.0, 0.5])).all() and (f.position <= 1.0).all()
        _assert_rotations(f.rotation, 1e-5)


def test_so3_log_exp_roundtrip():
    g = torch.Generator().manual_seed(3)
    for angle in [0.0, 1e-8, 0.5, 3.0, math.pi - 1e-9, math.pi]:
        axis = torch.randn(3, generator=g, dtype=torch.float64)
        w = angle * axis / axis.norm()
        R = so3_exp(w)
        torch.testing.assert_close(so3_exp(so3_log(R)), R, atol=1e-7, rtol=0)


# ---- demonstrator ---------------------------------------------------------------------


@pytest.mark.parametrize("dim", [2, 3])
def test_demonstration_reaches_between_frames(dim):
    g = torch.Generator().manual_seed(10 + dim)
    start = random_frame(g, dim, dtype=torch.float64)
    goal = random_frame(g, dim, dtype=torch.float64)
    demo = demonstrate(start, goal, n=200, generator=g, wiggle=0.15)
    assert isinstance(demo, DemonstratedMotion)
    assert demo.positions.shape == (200, dim) and demo.velocities.shape == (200, dim)
    assert demo.orientations.shape == (200, dim, dim) and demo.times.shape == (200,)
    torch.testing.assert_close(demo.positions[0], start.position)
    torch.testing.assert_close(demo.positions[-1], goal.position)

    speed = demo.velocities.norm(dim=-1)
    assert speed[0] < 1e-9 and speed[-1] < 1e-9
    assert speed[1] < 0.01 * speed.max() and speed[-2] < 0.01 * speed.max()
    # Bell-shaped: the peak is in the middle part of the motion.
    assert 40 < int(speed.argmax()) < 160

    # Leave along the start frame's +x axis, arrive along the goal frame's +x axis.
    assert _angle_between(demo.positions[1] - demo.positions[0], start.x_axis) < 2.0
    assert _angle_between(demo.positions[-1] - demo.positions[-2], goal.x_axis) < 2.0

    # Velocities agree with finite differences of the positions over the times.
    fd = torch.gradient(demo.positions, spacing=(demo.times,), dim=0)[0]
    assert (fd - demo.velocities).abs().max() < 0.02 * speed.max()

    _assert_rotations(demo.orientations, 1e-9)
    torch.testing.assert_close(demo.orientations[0], start.rotation)
    torch.testing.assert_close(demo.orientations[-1], goal.rotation)
    # Interpolation is continuous: consecutive orientations are close.
    steps = torch.linalg.matrix_norm(demo.orientations.diff(dim=0))
    assert steps.max() < 0.1


def test_demonstration_float32_and_velocity_directions():
    g = torch.Generator().manual_seed(4)
    start, goal = random_frame(g, 2), random_frame(g, 2)
    demo = demonstrate(start, goal, generator=g)
    assert demo.positions.dtype == torch.float32
    assert _angle_between(demo.velocities[1], start.x_axis) < 1.0
    assert _angle_between(demo.velocities[-2], goal.x_axis) < 1.0
    _assert_rotations(demo.orientations, 1e-5)


def test_orientation_takes_shortest_arc_in_2d():
    start = Frame.from_2d(0.0, 0.0, math.radians(170), dtype=torch.float64)
    goal = Frame.from_2d(1.0, 0.0, math.radians(-170), dtype=torch.float64)
    demo = demonstrate(start, goal, n=101, wiggle=0.0)
    headings = torch.atan2(demo.orientations[:, 1, 0], demo.orientations[:, 0, 0])
    # Goes through 180 degrees (20 degree turn), not through 0 (340 degree turn).
    assert (headings.abs() > math.radians(169.9)).all()


def test_same_seed_same_demo_and_different_seed_differs():
    start = Frame.from_2d(0.0, 0.0, 0.0)
    goal = Frame.from_2d(1.0, 1.0, 1.0)
    d1 = demonstrate(start, goal, generator=torch.Generator().manual_seed(7))
    d2 = demonstrate(start, goal, generator=torch.Generator().manual_seed(7))
    d3 = demonstrate(start, goal, generator=torch.Generator().manual_seed(8))
    assert torch.equal(d1.positions, d2.positions) and torch.equal(d1.orientations, d2.orientations)
    assert not torch.allclose(d1.positions, d3.positions)


def test_wiggle_is_bounded_and_lateral():
    start = Frame.from_2d(0.0, 0.0, 0.0, dtype=torch.float64)
    goal = Frame.from_2d(2.0, 0.0, 0.0, dtype=torch.float64)
    straight = demonstrate(start, goal, wiggle=0.0)
    assert straight.positions[:, 1].abs().max() < 1e-12  # Hermite with aligned tangents: a line
    wiggly = demonstrate(start, goal, wiggle=0.1, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(wiggly.positions[:, 0], straight.positions[:, 0])  # lateral only
    assert 0 < wiggly.positions[:, 1].abs().max() <= 0.1 * 2.0 + 1e-12


def test_demonstrate_bad_input():
    f2 = Frame.from_2d(0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="same dimension"):
        demonstrate(f2, Frame.from_3d([1.0, 0.0, 0.0], torch.eye(3)))
    with pytest.raises(ValueError, match="same position"):
        demonstrate(f2, Frame.from_2d(0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="n >= 2"):
        demonstrate(f2, Frame.from_2d(1.0, 0.0, 1.0), n=1)


# ---- LASA -----------------------------------------------------------------------------


def test_lasa_angle_loads_with_frames_at_its_ends():
    assert "Angle" in LASA_SHAPES and len(LASA_SHAPES) >= 20
    demo = load_lasa("Angle", demo=1, n=150)
    assert demo.positions.shape == (150, 2) and demo.times.shape == (150,)
    assert (demo.times.diff() > 0).all()
    torch.testing.assert_close(demo.times.diff(), torch.full((149,), float(demo.times[1])), atol=1e-5, rtol=1e-4)
    # LASA demos end at the origin; default scale 0.01 keeps the drawing within ~[-1, 1].
    torch.testing.assert_close(demo.positions[-1], torch.zeros(2), atol=1e-6, rtol=0)
    assert demo.positions.abs().max() < 1.0
    start, goal = lasa_frames(demo)
    torch.testing.assert_close(start.position, demo.positions[0])
    torch.testing.assert_close(goal.position, demo.positions[-1])
    # The frames point along the motion at the two ends.
    assert _angle_between(demo.positions[5] - demo.positions[0], start.x_axis) < 15.0
    assert _angle_between(demo.positions[-1] - demo.positions[-6], goal.x_axis) < 15.0
    # Orientations are rotations that match the frames at the ends.
    _assert_rotations(demo.orientations, 1e-5)
    torch.testing.assert_close(demo.orientations[0], start.rotation, atol=1e-5, rtol=0)
    torch.testing.assert_close(demo.orientations[-1], goal.rotation, atol=1e-5, rtol=0)


def test_lasa_scale_and_errors():
    mm = load_lasa("Angle", n=50, scale=1.0)
    m = load_lasa("Angle", n=50, scale=1e-3)
    torch.testing.assert_close(m.positions, 1e-3 * mm.positions, atol=1e-7, rtol=1e-5)
    with pytest.raises(ValueError, match="valid names: Angle"):
        load_lasa("NoSuchShape")
    with pytest.raises(ValueError, match="demo must be"):
        load_lasa("Angle", demo=7)


def test_frames_task_scenes_and_keypoints():
    task = FramesTask(n_points=40)
    lasa = task.sample_scenes("lasa", len(LASA_MOVES))
    source = task.source_scene()
    assert all(
        torch.equal(s.demo.positions, source.demo.positions) for s in lasa
    )  # moved frames, the same demonstration
    assert task.keypoints(lasa[0]).shape == (10, 2) and not torch.allclose(
        task.keypoints(lasa[0]), task.keypoints(source)
    )
    assert task.sample_scene("random", 2, seed=1).as_dict() == task.sample_scenes("random", 3, seed=1)[2].as_dict()
    with pytest.raises(ValueError, match="lasa condition has 2 scenes"):
        task.sample_scenes("lasa", 3)
    with pytest.raises(ValueError, match="frames has no condition"):
        task.sample_scene("moved", 0)
    with pytest.raises(ValueError, match="frame_size must be > 0"):
        FramesTask(frame_size=0.0)
