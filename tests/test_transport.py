"""What moves through a transportation map (kpflow.transport) and the rotation helpers (kpflow.geometry.rotations),
checked against closed-form expectations, finite differences and scipy."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from kpflow.geometry.rotations import matrix_to_quat, nearest_rotation, quat_to_matrix
from kpflow.maps import AffineMap, GPMap, ILWRMap
from kpflow.transport import (
    TransportedTrajectory,
    transport_covariances,
    transport_orientations,
    transport_positions,
    transport_quaternions,
    transport_stiffness,
    transport_trajectory,
    transport_velocities,
)
from tests.helpers import keypoint_pair, rotation

F64 = torch.float64
MAPS = {"ilwr": ILWRMap, "gp": GPMap}


def curve(t: torch.Tensor, d: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A smooth closed curve inside the [0, 1]^d keypoint region and its analytic velocity dx/dt."""
    cols = [0.5 + 0.3 * torch.cos(t), 0.5 + 0.2 * torch.sin(2 * t), 0.5 + 0.25 * torch.sin(t) * torch.cos(t)][:d]
    vels = [-0.3 * torch.sin(t), 0.4 * torch.cos(2 * t), 0.25 * torch.cos(2 * t)][:d]
    return torch.stack(cols, -1), torch.stack(vels, -1)


def random_rotations(n: int, d: int, seed: int) -> torch.Tensor:
    if d == 3:
        return torch.from_numpy(Rotation.random(n, random_state=seed).as_matrix())
    a = torch.rand(n, generator=torch.Generator().manual_seed(seed), dtype=F64) * 2 * math.pi
    return torch.stack([torch.stack([a.cos(), -a.sin()], -1), torch.stack([a.sin(), a.cos()], -1)], -2)


def random_spd(n: int, d: int, seed: int) -> torch.Tensor:
    m = torch.randn(n, d, d, generator=torch.Generator().manual_seed(seed), dtype=F64)
    return m @ m.transpose(-1, -2) + 0.1 * torch.eye(d, dtype=F64)


def assert_proper_rotations(r: torch.Tensor, atol: float = 1e-10) -> None:
    eye = torch.eye(r.shape[-1], dtype=r.dtype).expand_as(r)
    torch.testing.assert_close(r.transpose(-1, -2) @ r, eye, atol=atol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(r.shape[:-2], dtype=r.dtype), atol=atol, rtol=0)


def same_quaternion(a: torch.Tensor, b: torch.Tensor, atol: float = 1e-10) -> None:
    """q and -q are the same rotation: compare up to sign."""
    sign = torch.where((a * b).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(a.dtype)
    torch.testing.assert_close(a, sign * b, atol=atol, rtol=0)


# ------------------------------------------------------------------ velocities = derivative of the transported path
@pytest.mark.parametrize("name", MAPS)
@pytest.mark.parametrize("d", [2, 3])
def test_velocities_are_the_derivative_of_the_transported_curve(name, d):
    src, tgt = keypoint_pair(d, n=15)
    phi = MAPS[name]().fit(src, tgt)
    t = torch.linspace(0, 2 * math.pi, 40, dtype=F64)
    x, v = curve(t, d)
    h = 1e-5
    fd = (transport_positions(phi, curve(t + h, d)[0]) - transport_positions(phi, curve(t - h, d)[0])) / (2 * h)
    pushed = transport_velocities(phi, x, v)
    assert pushed.shape == x.shape
    torch.testing.assert_close(pushed, fd, atol=1e-7, rtol=1e-6)
    # the map is not rigid, so this is not just v rotated
    assert (pushed.norm(dim=-1) - v.norm(dim=-1)).abs().max() > 1e-3


def test_velocities_accept_leading_dimensions_and_a_given_jacobian():
    src, tgt = keypoint_pair(2)
    phi = ILWRMap().fit(src, tgt)
    x, v = curve(torch.linspace(0, 6, 24, dtype=F64), 2)
    x, v = x.reshape(2, 3, 4, 2), v.reshape(2, 3, 4, 2)
    out = transport_velocities(phi, x, v)
    assert out.shape == (2, 3, 4, 2)
    torch.testing.assert_close(out, transport_velocities(phi, x, v, jac=phi.jacobian(x)), atol=0, rtol=0)
    torch.testing.assert_close(out[1, 2], transport_velocities(phi, x[1, 2], v[1, 2]), atol=1e-12, rtol=0)


# ------------------------------------------------------------------ rigid and similarity maps: closed forms
def fitted_similarity(d: int, angle: float | None, scale: float, kind: str) -> tuple[AffineMap, torch.Tensor]:
    """An AffineMap fitted to keypoints moved by x -> scale Q x + shift (Q = helpers.rotation, tilted in 3-D;
    the identity when ``angle`` is None)."""
    src, _ = keypoint_pair(d, n=10)
    q = torch.eye(d, dtype=F64) if angle is None else rotation(d, angle)
    shift = torch.arange(1, d + 1, dtype=F64) * 0.3
    phi = AffineMap(kind).fit(src, scale * src @ q.T + shift)
    torch.testing.assert_close(phi.A[0], scale * q, atol=1e-10, rtol=0)
    return phi, q


@pytest.mark.parametrize("d", [2, 3])
def test_rigid_map_closed_forms(d):
    phi, q = fitted_similarity(d, 2.2, 1.0, "rigid")
    x = torch.rand(6, d, generator=torch.Generator().manual_seed(1), dtype=F64)
    r, s, k = random_rotations(6, d, 2), random_spd(6, d, 3), random_spd(6, d, 4)
    v = torch.randn(6, d, generator=torch.Generator().manual_seed(5), dtype=F64)
    torch.testing.assert_close(transport_velocities(phi, x, v), v @ q.T, atol=1e-10, rtol=0)
    torch.testing.assert_close(transport_orientations(phi, x, r), q @ r, atol=1e-10, rtol=0)
    torch.testing.assert_close(transport_covariances(phi, x, s), q @ s @ q.T, atol=1e-10, rtol=0)
    qkq = q @ k @ q.T
    torch.testing.assert_close(transport_stiffness(phi, x, k), qkq, atol=1e-10, rtol=0)  # default: rotation
    torch.testing.assert_close(transport_stiffness(phi, x, k, mode="rotation"), qkq, atol=1e-10, rtol=0)
    torch.testing.assert_close(transport_stiffness(phi, x, k, mode="covector"), qkq, atol=1e-10, rtol=0)


@pytest.mark.parametrize("d", [2, 3])
def test_pure_scaling_map(d):
    phi, _ = fitted_similarity(d, None, 2.0, "similarity")
    torch.testing.assert_close(phi.A[0], 2.0 * torch.eye(d, dtype=F64), atol=1e-10, rtol=0)
    x = torch.rand(5, d, generator=torch.Generator().manual_seed(1), dtype=F64)
    r, s, k = random_rotations(5, d, 2), random_spd(5, d, 3), random_spd(5, d, 4)
    v = torch.randn(5, d, generator=torch.Generator().manual_seed(5), dtype=F64)
    torch.testing.assert_close(transport_velocities(phi, x, v), 2 * v, atol=1e-10, rtol=0)
    torch.testing.assert_close(transport_orientations(phi, x, r), r, atol=1e-10, rtol=0)
    torch.testing.assert_close(transport_covariances(phi, x, s), 4 * s, atol=1e-10, rtol=0)
    torch.testing.assert_close(transport_stiffness(phi, x, k, mode="rotation"), k, atol=1e-10, rtol=0)
    torch.testing.assert_close(transport_stiffness(phi, x, k, mode="covector"), k / 4, atol=1e-10, rtol=0)


@pytest.mark.parametrize("d", [2, 3])
def test_rotation_and_scaling_map(d):
    phi, q = fitted_similarity(d, -1.3, 0.5, "similarity")
    x = torch.rand(5, d, generator=torch.Generator().manual_seed(1), dtype=F64)
    r, s, k = random_rotations(5, d, 2), random_spd(5, d, 3), random_spd(5, d, 4)
    torch.testing.assert_close(transport_orientations(phi, x, r), q @ r, atol=1e-10, rtol=0)
    torch.testing.assert_close(transport_covariances(phi, x, s), 0.25 * q @ s @ q.T, atol=1e-10, rtol=0)
    torch.testing.assert_close(transport_stiffness(phi, x, k, mode="rotation"), q @ k @ q.T, atol=1e-10, rtol=0)
    torch.testing.assert_close(transport_stiffness(phi, x, k, mode="covector"), 4 * q @ k @ q.T, atol=1e-10, rtol=0)


def test_general_map_stiffness_modes():
    """Under a non-linear map: covector keeps the elastic energy, rotation keeps the stiffness magnitudes."""
    src, tgt = keypoint_pair(3, n=15)
    phi = ILWRMap().fit(src, tgt)
    x, _ = curve(torch.linspace(0, 6, 20, dtype=F64), 3)
    k = random_spd(20, 3, 0)
    dx = torch.randn(20, 3, 1, generator=torch.Generator().manual_seed(1), dtype=F64)
    jac = phi.jacobian(x)
    kc = transport_stiffness(phi, x, k, mode="covector")
    energy = (dx.transpose(-1, -2) @ k @ dx).squeeze()
    moved = jac @ dx
    torch.testing.assert_close((moved.transpose(-1, -2) @ kc @ moved).squeeze(), energy, atol=1e-10, rtol=1e-9)
    kr = transport_stiffness(phi, x, k, mode="rotation")
    q = nearest_rotation(jac)
    torch.testing.assert_close(kr, q @ k @ q.transpose(-1, -2), atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.eigvalsh(kr), torch.linalg.eigvalsh(k), atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(kr, kr.transpose(-1, -2), atol=1e-12, rtol=0)
    # orientations go through the same rotation; covariances through J
    r = random_rotations(20, 3, 2)
    torch.testing.assert_close(transport_orientations(phi, x, r), q @ r, atol=1e-12, rtol=0)
    s = random_spd(20, 3, 3)
    torch.testing.assert_close(transport_covariances(phi, x, s), jac @ s @ jac.transpose(-1, -2), atol=1e-12, rtol=0)


@pytest.mark.parametrize("mode", ["Rotation", "contravariant", ""])
def test_unknown_stiffness_mode_raises(mode):
    phi, _ = fitted_similarity(2, 0.3, 1.0, "rigid")
    with pytest.raises(ValueError, match="unknown stiffness mode"):
        transport_stiffness(phi, torch.zeros(1, 2, dtype=F64), torch.eye(2, dtype=F64)[None], mode=mode)


# ------------------------------------------------------------------ quaternions
def test_quat_to_matrix_matches_scipy_xyzw():
    q = torch.from_numpy(Rotation.random(20, random_state=0).as_quat())  # scipy: (x, y, z, w)
    torch.testing.assert_close(
        quat_to_matrix(q), torch.from_numpy(Rotation.from_quat(q.numpy()).as_matrix()), atol=1e-12, rtol=0
    )
    # scalar-first order would be a different rotation: the order matters
    wxyz = q[:, [3, 0, 1, 2]]
    assert (quat_to_matrix(wxyz) - quat_to_matrix(q)).abs().amax() > 0.1
    # not unit: normalised first; q and -q give the same matrix
    torch.testing.assert_close(quat_to_matrix(3.0 * q), quat_to_matrix(q), atol=1e-12, rtol=0)
    torch.testing.assert_close(quat_to_matrix(-q), quat_to_matrix(q), atol=1e-12, rtol=0)


def test_matrix_to_quat_matches_scipy_and_round_trips():
    rots = Rotation.random(50, random_state=1)
    # and the awkward ones: half turns about each axis and about diagonals (w = 0), near-half turns, identity
    special = Rotation.from_rotvec(
        [
            [math.pi, 0, 0],
            [0, math.pi, 0],
            [0, 0, math.pi],
            [math.pi / math.sqrt(2), math.pi / math.sqrt(2), 0],
            [3.1, 0, 0],
            [0, -3.1, 0],
            [0, 0, 3.1],
            [0, 0, 0],
            [1e-9, 0, 0],
        ]
    )
    for r in (rots, special):
        m = torch.from_numpy(r.as_matrix())
        q = matrix_to_quat(m)
        torch.testing.assert_close(q.norm(dim=-1), torch.ones(len(m), dtype=F64), atol=1e-12, rtol=0)
        assert (q[:, 3] >= 0).all()
        same_quaternion(q, torch.from_numpy(r.as_quat()))
        torch.testing.assert_close(quat_to_matrix(q), m, atol=1e-12, rtol=0)
    q = torch.from_numpy(rots.as_quat(canonical=True))  # canonical: w >= 0
    torch.testing.assert_close(matrix_to_quat(quat_to_matrix(q)), q, atol=1e-12, rtol=0)


def test_quaternion_helpers_keep_leading_dimensions():
    q = torch.from_numpy(Rotation.random(24, random_state=2).as_quat()).reshape(2, 3, 4, 4)
    m = quat_to_matrix(q)
    assert m.shape == (2, 3, 4, 3, 3)
    assert matrix_to_quat(m).shape == (2, 3, 4, 4)


def test_transport_quaternions_under_a_rigid_map_matches_scipy_composition():
    phi, q_map = fitted_similarity(3, 0.8, 1.0, "rigid")
    x = torch.rand(10, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    rots = Rotation.random(10, random_state=3)
    out = transport_quaternions(phi, x, torch.from_numpy(rots.as_quat()))
    expected = (Rotation.from_matrix(q_map.numpy()) * rots).as_quat(canonical=True)  # rotation Q R, (x, y, z, w)
    torch.testing.assert_close(out, torch.from_numpy(expected), atol=1e-10, rtol=0)


def test_transport_quaternions_agrees_with_orientations_under_a_nonlinear_map():
    src, tgt = keypoint_pair(3, n=15)
    phi = ILWRMap().fit(src, tgt)
    x, _ = curve(torch.linspace(0, 6, 12, dtype=F64), 3)
    quats = torch.from_numpy(Rotation.random(12, random_state=4).as_quat())
    out = transport_quaternions(phi, x, quats)
    torch.testing.assert_close(out.norm(dim=-1), torch.ones(12, dtype=F64), atol=1e-12, rtol=0)
    torch.testing.assert_close(
        quat_to_matrix(out), transport_orientations(phi, x, quat_to_matrix(quats)), atol=1e-12, rtol=0
    )
    # a quaternion and its negative are the same orientation and transport to the same result
    torch.testing.assert_close(transport_quaternions(phi, x, -quats), out, atol=1e-12, rtol=0)


# ------------------------------------------------------------------ nearest rotation
def random_matrices(n: int, d: int, seed: int) -> torch.Tensor:
    """Gaussian matrices, every other one with its first row negated so half have det < 0 for sure."""
    m = torch.randn(n, d, d, generator=torch.Generator().manual_seed(seed), dtype=F64)
    flip = torch.where(torch.linalg.det(m) > 0, 1.0, -1.0).to(F64)
    flip = flip * torch.tensor([1.0, -1.0], dtype=F64).repeat(n // 2 + 1)[:n]
    m[:, 0] = m[:, 0] * flip[:, None]
    assert (torch.linalg.det(m) < 0).sum() == n // 2
    return m


@pytest.mark.parametrize("d", [2, 3])
def test_nearest_rotation_is_proper(d):
    m = random_matrices(200, d, 0)
    r = nearest_rotation(m)
    assert_proper_rotations(r)


def test_nearest_rotation_2d_closed_form():
    # argmin_R |M - R|_F over 2-D rotations maximises tr(R^T M) = cos(a)(m00 + m11) + sin(a)(m10 - m01)
    m = random_matrices(200, 2, 1)
    a = torch.atan2(m[:, 1, 0] - m[:, 0, 1], m[:, 0, 0] + m[:, 1, 1])
    expected = torch.stack([torch.stack([a.cos(), -a.sin()], -1), torch.stack([a.sin(), a.cos()], -1)], -2)
    torch.testing.assert_close(nearest_rotation(m), expected, atol=1e-10, rtol=0)


def test_nearest_rotation_3d_matches_scipy_kabsch():
    # scipy's align_vectors(a, b) maximises tr(R^T sum_i a_i b_i^T); with b_i = e_i and a_i = column i of M that is M
    m = random_matrices(60, 3, 2)
    r = nearest_rotation(m)
    for mi, ri in zip(m, r):
        ref, _ = Rotation.align_vectors(mi.T.numpy(), torch.eye(3, dtype=F64).numpy())
        torch.testing.assert_close(ri, torch.from_numpy(ref.as_matrix()), atol=1e-8, rtol=0)


@pytest.mark.parametrize("d", [2, 3])
def test_nearest_rotation_is_identity_on_rotations_and_ignores_positive_scale(d):
    r = random_rotations(50, d, 3)
    torch.testing.assert_close(nearest_rotation(r), r, atol=1e-12, rtol=0)
    torch.testing.assert_close(nearest_rotation(3.7 * r), r, atol=1e-12, rtol=0)
    # a symmetric positive-definite stretch applied on the right does not change the polar factor
    torch.testing.assert_close(nearest_rotation(r @ random_spd(50, d, 4)), r, atol=1e-10, rtol=0)


@settings(max_examples=40)
@given(seed=st.integers(0, 100_000), d=st.sampled_from([2, 3]), shape=st.sampled_from([(), (4,), (2, 3)]))
def test_nearest_rotation_property(seed, d, shape):
    m = torch.randn(*shape, d, d, generator=torch.Generator().manual_seed(seed), dtype=F64)
    r = nearest_rotation(m)
    assert r.shape == m.shape
    assert_proper_rotations(r)
    # locally optimal: no small rotation of R gets closer to M
    w = 1e-3 * torch.randn(*shape, d, d, generator=torch.Generator().manual_seed(seed + 1), dtype=F64)
    nearby = r @ torch.linalg.matrix_exp(w - w.transpose(-1, -2))
    assert ((m - nearby).square().sum((-1, -2)) >= (m - r).square().sum((-1, -2)) - 1e-12).all()


def test_nearest_rotation_float32():
    m = random_matrices(20, 3, 5).float()
    r = nearest_rotation(m)
    assert r.dtype == torch.float32
    assert_proper_rotations(r, atol=1e-5)


# ------------------------------------------------------------------ whole trajectories
@pytest.fixture(scope="module")
def fitted_maps():
    src, tgt = keypoint_pair(2)
    return {"ilwr": ILWRMap().fit(src, tgt), "gp": GPMap().fit(src, tgt)}


@pytest.mark.parametrize("name", MAPS)
def test_transport_trajectory_fields(fitted_maps, name):
    phi = fitted_maps[name]
    t = torch.linspace(0, 2 * math.pi, 30, dtype=F64)
    x, v = curve(t, 2)
    x = x * 1.6 - 0.3  # reaches outside the keypoints, where the uncertainty grows
    rots, k = random_rotations(30, 2, 0), random_spd(30, 2, 1)
    out = transport_trajectory(
        phi, x, velocities=v, orientations=rots, stiffness=k, n_samples=6, generator=torch.Generator().manual_seed(7)
    )
    assert isinstance(out, TransportedTrajectory)
    mean, var = phi.predict(x)
    torch.testing.assert_close(out.positions, mean, atol=0, rtol=0)
    torch.testing.assert_close(out.positions, phi(x), atol=1e-10, rtol=0)
    torch.testing.assert_close(out.std, var.sqrt(), atol=0, rtol=0)
    assert (out.std >= 0).all() and out.std.max() > 0
    assert out.std.shape == out.positions.shape == (30, 2)
    torch.testing.assert_close(out.velocities, transport_velocities(phi, x, v), atol=1e-12, rtol=0)
    torch.testing.assert_close(out.orientations, transport_orientations(phi, x, rots), atol=1e-12, rtol=0)
    assert_proper_rotations(out.orientations)
    torch.testing.assert_close(out.stiffness, transport_stiffness(phi, x, k, mode="rotation"), atol=1e-12, rtol=0)
    # samples: [n, T, D], the same draws as sample() with the same generator, scattered around the mean
    assert out.samples.shape == (6, 30, 2)
    torch.testing.assert_close(out.samples, phi.sample(x, 6, torch.Generator().manual_seed(7)), atol=1e-12, rtol=0)
    assert ((out.samples - mean).abs() <= 8 * out.std + 1e-9).all()
    assert (out.samples - mean).abs().max() > 0
    # k-sigma band edges
    lo, hi = out.band()
    torch.testing.assert_close(lo, mean - 2 * out.std, atol=1e-15, rtol=0)
    torch.testing.assert_close(hi, mean + 2 * out.std, atol=1e-15, rtol=0)
    lo3, hi3 = out.band(3.0)
    torch.testing.assert_close(hi3 - lo3, 6 * out.std, atol=1e-14, rtol=0)


@pytest.mark.parametrize("name", MAPS)
def test_transport_trajectory_optional_fields(fitted_maps, name):
    phi = fitted_maps[name]
    x, _ = curve(torch.linspace(0, 6, 10, dtype=F64), 2)
    out = transport_trajectory(phi, x)
    assert out.velocities is None and out.orientations is None and out.stiffness is None and out.samples is None
    torch.testing.assert_close(out.positions, phi.predict(x)[0], atol=0, rtol=0)
    only_v = transport_trajectory(phi, x, velocities=torch.ones_like(x))
    assert only_v.velocities.shape == (10, 2) and only_v.orientations is None and only_v.stiffness is None


def test_transport_trajectory_rigid_map_is_certain():
    phi, q = fitted_similarity(3, 1.1, 1.0, "rigid")
    x, v = curve(torch.linspace(0, 6, 15, dtype=F64), 3)
    rots = random_rotations(15, 3, 0)
    out = transport_trajectory(phi, x, velocities=v, orientations=rots, n_samples=3)
    torch.testing.assert_close(out.std, torch.zeros_like(x), atol=0, rtol=0)
    torch.testing.assert_close(out.samples, out.positions.expand(3, -1, -1), atol=0, rtol=0)
    torch.testing.assert_close(out.velocities, v @ q.T, atol=1e-10, rtol=0)
    torch.testing.assert_close(out.orientations, q @ rots, atol=1e-10, rtol=0)
    lo, hi = out.band()
    torch.testing.assert_close(lo, hi, atol=0, rtol=0)
