"""Policy transportation of a recorded demonstration acting on the map's uncertainty
(kpflow/policies/demo_transport.py): closed-form checks of the rigid fall-back and of stopping."""

import numpy as np
import pytest
import torch

from kpflow.maps import GPMap
from kpflow.policies.demo_transport import DemoTransportPolicy
from kpflow.trajectory import Keypoints, Trajectory


def _line_demo(n: int = 41):
    x = torch.linspace(0.0, 4.0, n, dtype=torch.float64)
    positions = torch.stack(
        [0.15 + x, 0.15 + 0.2 * x, 0.15 + 0 * x], -1
    ).numpy()  # from the keypoints' centre out to x = 4
    rotations = np.repeat(np.eye(3)[None], n, 0)
    return Trajectory(positions, rotations, np.zeros(n, bool), np.array(["move"] * n))


def _keypoints():
    g = torch.Generator().manual_seed(0)
    src = torch.rand(12, 3, generator=g, dtype=torch.float64) * 0.3
    tgt = src + 0.05 * torch.sin(6 * src) + torch.tensor([0.1, -0.05, 0.0], dtype=torch.float64)
    return Keypoints(src.numpy(), tgt.numpy())


def test_uncertain_steps_fall_back_to_the_rigid_motion():
    demo, kp = _line_demo(), _keypoints()
    plain, phi = DemoTransportPolicy(GPMap).plan(demo, kp)
    u = np.linalg.norm(plain.std, axis=1)
    max_std = 0.5 * u.max()
    gated, phi = DemoTransportPolicy(GPMap, max_std=max_std).plan(demo, kp)
    lam = np.clip(u / max_std - 1, 0, 1)
    rigid = phi.alignment(torch.as_tensor(demo.positions)).numpy().reshape(demo.positions.shape)
    np.testing.assert_allclose(gated.positions[lam == 0], plain.positions[lam == 0], atol=1e-12)  # sure: phi
    np.testing.assert_allclose(gated.positions[lam == 1], rigid[lam == 1], atol=1e-12)  # twice the threshold: rigid
    mid = (lam > 0) & (lam < 1)
    expected = (1 - lam[mid, None]) * plain.positions[mid] + lam[mid, None] * rigid[mid]
    np.testing.assert_allclose(gated.positions[mid], expected, atol=1e-12)
    assert (lam == 1).any() and (lam == 0).any()
    np.testing.assert_allclose(np.linalg.det(gated.rotations), 1.0, atol=1e-9)  # still rotations


def test_stop_ends_the_plan_before_the_first_uncertain_step():
    demo, kp = _line_demo(), _keypoints()
    plain, _ = DemoTransportPolicy(GPMap).plan(demo, kp)
    u = np.linalg.norm(plain.std, axis=1)
    policy = DemoTransportPolicy(GPMap, max_std=0.5 * u.max(), on_uncertain="stop")
    stopped, _ = policy.plan(demo, kp)
    first = int(np.flatnonzero(u > 0.5 * u.max())[0])
    assert policy.stopped_at == first == len(stopped) and 0 < first < len(demo)
    np.testing.assert_allclose(stopped.positions, plain.positions[:first], atol=1e-12)
    assert (
        DemoTransportPolicy(GPMap, max_std=10 * u.max(), on_uncertain="stop").plan(demo, kp)[0].positions.shape
        == plain.positions.shape
    )
    with pytest.raises(ValueError, match="on_uncertain must be one of"):
        DemoTransportPolicy(GPMap, max_std=1.0, on_uncertain="ask")
    with pytest.raises(ValueError, match="max_std must be > 0"):
        DemoTransportPolicy(GPMap, max_std=0.0)
