"""Online transport in 3-D (issue 41): transported K-CFM and policy transportation on a robosuite-like layout.

Synthetic Stack-like configurations (two cubes of 8 corners, the grip site and two finger pads) and end-effector
target chunks (position, 6-D rotation, gripper). An identity scene gives the bare policy's actions; a rigidly moved
scene moves positions and orientations by the same motion; under a nonlinear map (the cubes moved independently)
orientations stay rotations.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kpflow.core.policy import PolicyLayout
from kpflow.data.source_index import SourceIndex
from kpflow.geometry.rotations import matrix_to_rot6d, rot6d_to_matrix
from kpflow.maps import AffineMap, ILWRMap
from kpflow.policies.chunk_transport import TransportPolicy, transport_chunk
from kpflow.policies.kcfm.model import KCFM
from kpflow.policies.kcfm.policy import KCFMPolicy
from kpflow.policies.transported_kcfm import TransportedKCFMPolicy
from tests.helpers import cube_corners as _cube
from tests.helpers import random_kcfm_3d
from tests.helpers import yaw_matrix as _yaw

H, K = 8, 19
LAYOUT = PolicyLayout(K, 3, 10, {"cubeA": tuple(range(8)), "cubeB": tuple(range(8, 16)), "gripper": (16, 17, 18)},
                      {"objects": ("cubeA",), "goals": ("cubeB",), "robot": ("gripper",)}, rotation=True)  # fmt: skip
FIT_ON = list(LAYOUT.indices("objects", "goals"))


def _configurations(n: int = 60, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints ``[n, 19, 3]`` and chunks ``[n, H, 10]``: the jaws above cube A moving down towards it."""
    rng = np.random.default_rng(seed)
    keypoints, chunks = [], []
    for _ in range(n):
        a, b = (
            rng.uniform(-0.08, 0.08, 3) * [1, 1, 0] + [0, 0, 0.82],
            rng.uniform(-0.08, 0.08, 3) * [1, 1, 0] + [0.1, 0, 0.82],
        )
        grip = a + rng.uniform(-0.05, 0.05, 3) + [0, 0, 0.15]
        jaws = _yaw(rng.uniform(-0.5, 0.5)) @ np.diag([1.0, -1.0, -1.0])
        pads = grip + np.array([[0, 0.02, 0], [0, -0.02, 0]]) @ jaws.T
        keypoints.append(
            np.concatenate([_cube(a, rng.uniform(-0.7, 0.7)), _cube(b, rng.uniform(-0.7, 0.7)), grip[None], pads])
        )
        path = grip + np.linspace(0, 1, H)[:, None] * (a - grip)
        chunks.append(
            np.concatenate([path, np.repeat(matrix_to_rot6d(jaws)[None], H, 0), np.linspace(-1, 1, H)[:, None]], 1)
        )
    return np.asarray(keypoints), np.asarray(chunks)


@pytest.fixture(scope="module")
def index() -> SourceIndex:
    keypoints, chunks = _configurations()
    return SourceIndex(keypoints, chunks, LAYOUT.weights({"robot": 4.0}), LAYOUT.indices("objects"))


@pytest.fixture(scope="module")
def model(index) -> KCFM:
    """A 3-D K-CFM with two observation frames, random weights and the data's normalisation."""
    return random_kcfm_3d(index, K, H, n_obs=2)


def _moved(keypoints: np.ndarray, rot: np.ndarray, shift) -> np.ndarray:
    return keypoints @ rot.T + np.asarray(shift)


def _obs(now: np.ndarray, before: np.ndarray | None = None) -> dict:
    before = now if before is None else before
    return {"keypoints": now, "keypoints_history": np.stack([before, now])}


def test_in_an_identity_scene_the_transported_policy_acts_as_the_bare_one(model, index):
    bare = KCFMPolicy(model, steps=3, execute=H)
    transported = TransportedKCFMPolicy(model, index, ILWRMap, steps=3, execute=H, fit_on=FIT_ON, layout=LAYOUT)
    for i in (0, 17):
        scene = index.keypoints[i].astype(np.float64)
        before = scene.copy()
        before[16:] += 0.004  # the jaws moved since the frame before
        bare.reset(5), transported.reset(5)
        got, expected = transported.act(_obs(scene, before)), bare.act(_obs(scene, before))
        np.testing.assert_allclose(got[:, :3], expected[:, :3], atol=1e-9)
        # the 6-D rotation comes back as the first two columns of the rotation it stands for (rotations.rot6d_to_matrix)
        np.testing.assert_allclose(rot6d_to_matrix(got[:, 3:9]), rot6d_to_matrix(expected[:, 3:9]), atol=1e-9)
        np.testing.assert_array_equal(got[:, 9], expected[:, 9])
        assert transported.last_source == i


@pytest.mark.parametrize("make_map", [ILWRMap, lambda: AffineMap(kind="rigid")], ids=["ilwr", "rigid"])
def test_a_rigidly_moved_scene_moves_the_actions_by_the_same_motion(model, index, make_map):
    rot, shift = _yaw(0.9), np.array([0.12, -0.2, 0.0])
    bare = KCFMPolicy(model, steps=3, execute=H)
    transported = TransportedKCFMPolicy(model, index, make_map, steps=3, execute=H, fit_on=FIT_ON, layout=LAYOUT)
    source = index.keypoints[9].astype(np.float64)
    bare.reset(2), transported.reset(2)
    expected = bare.act(_obs(source))
    got = transported.act(_obs(_moved(source, rot, shift)))
    assert transported.last_source == 9
    np.testing.assert_allclose(got[:, :3], _moved(expected[:, :3], rot, shift), atol=1e-6)
    np.testing.assert_allclose(rot6d_to_matrix(got[:, 3:9]), rot @ rot6d_to_matrix(expected[:, 3:9]), atol=1e-6)
    np.testing.assert_array_equal(got[:, 9], expected[:, 9])  # the gripper is not spatial


def test_policy_transportation_moves_the_demonstrated_chunk_rigidly_with_the_scene(index):
    rot, shift = _yaw(-1.2), np.array([-0.05, 0.1, 0.0])
    policy = TransportPolicy(index, ILWRMap, execute=H, fit_on=FIT_ON, layout=LAYOUT)
    got = policy.act({"keypoints": _moved(index.keypoints[3].astype(np.float64), rot, shift)})
    chunk = index.chunks[3].astype(np.float64)
    np.testing.assert_allclose(got[:, :3], _moved(chunk[:, :3], rot, shift), atol=1e-6)
    np.testing.assert_allclose(rot6d_to_matrix(got[:, 3:9]), rot @ rot6d_to_matrix(chunk[:, 3:9]), atol=1e-6)
    np.testing.assert_array_equal(got[:, 9], chunk[:, 9])


def test_under_a_nonlinear_map_orientations_stay_rotations(model, index):
    """Cube B moved and turned apart from cube A: ILWR bends space between them, its Jacobian is no rotation, and the
    pushed-forward end-effector orientations are still exactly rotations (polar factor)."""
    source = index.keypoints[4].astype(np.float64)
    target = source.copy()
    target[8:16] = _moved(source[8:16] - source[8:16].mean(0), _yaw(0.6), source[8:16].mean(0) + [0.15, 0.1, 0.0])
    phi = ILWRMap().fit(torch.from_numpy(source[FIT_ON]), torch.from_numpy(target[FIT_ON]))
    chunk = index.chunks[4].astype(np.float64).copy()
    chunk[:, :3] = np.linspace(source[:8].mean(0), source[8:16].mean(0), H)  # from cube A to cube B
    jac = phi.jacobian(torch.from_numpy(chunk[:, :3])).numpy()
    assert np.abs(jac.transpose(0, 2, 1) @ jac - np.eye(3)).max() > 0.05  # not a rigid motion there
    out = transport_chunk(phi, chunk, 3, rotation=True)
    a1, a2 = out[:, 3:6], out[:, 6:9]
    np.testing.assert_allclose(np.linalg.norm(a1, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(a2, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose((a1 * a2).sum(1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot6d_to_matrix(out[:, 3:9])), 1.0, atol=1e-12)
    transported = TransportedKCFMPolicy(model, index, ILWRMap, steps=3, execute=H, fit_on=FIT_ON, layout=LAYOUT)
    actions = transported.act(_obs(target))
    rots = rot6d_to_matrix(actions[:, 3:9])
    np.testing.assert_allclose(rots.transpose(0, 2, 1) @ rots, np.broadcast_to(np.eye(3), rots.shape), atol=1e-9)


def test_the_layout_names_groups_and_roles_and_refuses_what_it_cannot_be():
    assert LAYOUT.indices("robot") == (16, 17, 18) and LAYOUT.indices("cubeB", "gripper") == (*range(8, 16), 16, 17, 18)
    np.testing.assert_array_equal(LAYOUT.weights({"robot": 4.0, "cubeA": 0.5}), [0.5] * 8 + [1.0] * 8 + [4.0] * 3)
    with pytest.raises(ValueError, match="unknown keypoint group 'hand'"):
        LAYOUT.indices("hand")
    with pytest.raises(ValueError, match="must name each of the 4 keypoints exactly once"):
        PolicyLayout(4, 3, 10, {"a": (0, 1), "b": (1, 2)})
    with pytest.raises(ValueError, match="cannot start with a 3-D position and a 6-D rotation"):
        PolicyLayout(4, 3, 7, rotation=True)
    with pytest.raises(ValueError, match="layout names 4 keypoints; the source index holds 19"):
        TransportPolicy(SourceIndex(*_configurations(3)), execute=H, layout=PolicyLayout(4, 3, 10))
