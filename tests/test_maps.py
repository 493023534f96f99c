"""Properties every transportation map family must have (issue 2, section 5)."""

import functools

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kpflow.maps import AffineMap, EnsembleMap, FlowMap, GPMap, ILWRMap, MLPMap
from kpflow.maps.base import jacobian_autograd
from tests.helpers import grid, keypoint_pair, rotation

FAMILIES = {
    "affine": lambda: AffineMap("rigid"),
    "ilwr": lambda: ILWRMap(),
    "gp": lambda: GPMap(),
    "flow": lambda: FlowMap(steps=100),
    "mlp": lambda: MLPMap(steps=100),
    "ensemble": lambda: EnsembleMap(functools.partial(MLPMap, steps=60), n_members=3),
}
BIJECTIVE = ["affine", "ilwr", "flow"]


@pytest.mark.parametrize("name", FAMILIES)
@pytest.mark.parametrize("d", [2, 3])
def test_identity_when_source_equals_target(name, d):
    src, _ = keypoint_pair(d)
    phi = FAMILIES[name]().fit(src, src)
    x = grid(d, n=6)
    torch.testing.assert_close(phi(x), x, atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", ["ilwr", "gp"])
@pytest.mark.parametrize("d", [2, 3])
def test_interpolates_keypoints(name, d):
    src, tgt = keypoint_pair(d)
    phi = (ILWRMap(n_steps=300) if name == "ilwr" else GPMap()).fit(src, tgt)
    err = (phi(src) - tgt).norm(dim=-1).max()
    assert err < 1e-3, err  # deformation is ~0.08, keypoint spacing ~0.2


@pytest.mark.parametrize("name", ["ilwr", "gp", "flow", "mlp"])
@pytest.mark.parametrize("kind", ["rigid", "similarity"])
def test_recovers_rigid_and_similarity_motion(name, kind):
    src, _ = keypoint_pair(3)
    scale = 1.0 if kind == "rigid" else 1.7
    tgt = scale * src @ rotation(3, 2.0).T + torch.tensor([0.5, -1.0, 2.0], dtype=src.dtype)
    phi = {"ilwr": ILWRMap, "gp": GPMap, "flow": functools.partial(FlowMap, steps=50), "mlp": functools.partial(MLPMap, steps=50)}[name](alignment=kind).fit(src, tgt)
    x = grid(3, n=5)
    expected = scale * x @ rotation(3, 2.0).T + torch.tensor([0.5, -1.0, 2.0], dtype=src.dtype)
    torch.testing.assert_close(phi(x), expected, atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", BIJECTIVE)
@pytest.mark.parametrize("d", [2, 3])
def test_inverse_round_trip_on_wide_grid(name, d):
    src, tgt = keypoint_pair(d)
    phi = FAMILIES[name]().fit(src, tgt)
    x = grid(d, n=15 if d == 2 else 8)
    torch.testing.assert_close(phi.inverse(phi(x)), x, atol=1e-5, rtol=0)
    torch.testing.assert_close(phi(phi.inverse(x)), x, atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", ["ilwr", "flow"])
@pytest.mark.parametrize("d", [2, 3])
def test_positive_jacobian_determinant(name, d):
    src, tgt = keypoint_pair(d)
    phi = FAMILIES[name]().fit(src, tgt)
    assert torch.linalg.det(phi.jacobian(grid(d, n=15 if d == 2 else 8))).min() > 0


def test_ilwr_steps_respect_diffeomorphism_bound():
    src, tgt = keypoint_pair(2)
    phi = ILWRMap().fit(src, tgt)
    rho_v = (-phi.neg_rho2).sqrt() * phi.vectors.norm(dim=-1)
    assert (rho_v < (torch.e / 2) ** 0.5).all()


@pytest.mark.parametrize("name", FAMILIES)
def test_jacobian_matches_finite_differences(name):
    src, tgt = keypoint_pair(2)
    phi = FAMILIES[name]().fit(src, tgt)
    x = grid(2, n=5)
    h = 1e-6
    eye = torch.eye(2, dtype=x.dtype)
    fd = torch.stack([(phi(x + h * eye[j]) - phi(x - h * eye[j])) / (2 * h) for j in range(2)], -1)
    torch.testing.assert_close(phi.jacobian(x), fd, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(phi.jacobian(x), jacobian_autograd(phi._forward, x[None])[0], atol=1e-8, rtol=1e-8)


def test_gp_variance_noise_at_keypoints_prior_far_away():
    src, tgt = keypoint_pair(2)
    phi = GPMap().fit(src, tgt)
    _, var_kp = phi.predict(src)
    assert var_kp.max() <= 2 * phi.gp.noise + 1e-12
    far = torch.tensor([[40.0, -30.0]], dtype=src.dtype)
    mean, var = phi.predict(far)
    torch.testing.assert_close(var, phi.gp.outputscale.expand(1, 2), rtol=1e-3, atol=0)
    torch.testing.assert_close(mean, phi.alignment(far), atol=1e-6, rtol=0)  # zero-transport prior
    # the Jacobian's variance follows: ~0 changes far away is the prior s^2 / l^2
    jv = phi.jacobian_variance(far)
    torch.testing.assert_close(jv, (phi.gp.outputscale / phi.gp.lengthscale**2).expand(1, 2, 2), rtol=1e-3, atol=0)


def test_gp_samples_are_joint_and_centred():
    src, tgt = keypoint_pair(2)
    phi = GPMap().fit(src, tgt)
    x = grid(2, n=6)
    s = phi.sample(x, 400, generator=torch.Generator().manual_seed(0))
    mean, var = phi.predict(x)
    assert s.shape == (400, *x.shape)
    torch.testing.assert_close(s.mean(0), mean, atol=4 * var.sqrt().max() / 20 + 1e-6, rtol=0)
    torch.testing.assert_close(s.var(0), var, rtol=0.35, atol=1e-8)


@pytest.mark.parametrize("name", ["ilwr", "ensemble"])
def test_uncertainty_grows_away_from_keypoints(name):
    src, tgt = keypoint_pair(2)
    phi = FAMILIES[name]().fit(src, tgt)
    _, near = phi.predict(src)
    _, far = phi.predict(torch.tensor([[3.0, 3.0]], dtype=src.dtype))
    assert far.mean() > 5 * near.mean()


@pytest.mark.parametrize("name", ["affine", "ilwr"])
def test_batched_fit_equals_looped(name):
    srcs = torch.stack([keypoint_pair(2, seed=s)[0] for s in range(4)])
    _, tgt = keypoint_pair(2)
    x = grid(2, n=5)
    batched = FAMILIES[name]().fit(srcs, tgt)
    y = batched(x)  # one query for every map: [4, M, 2]
    per = batched(x.expand(4, -1, -1))
    for b in range(4):
        single = FAMILIES[name]().fit(srcs[b], tgt)
        torch.testing.assert_close(y[b], single(x), atol=1e-10, rtol=0)
        torch.testing.assert_close(per[b], single(x), atol=1e-10, rtol=0)
        torch.testing.assert_close(batched.jacobian(x)[b], single.jacobian(x), atol=1e-10, rtol=0)


@pytest.mark.parametrize("name", FAMILIES)
def test_leading_dimensions_and_float32(name):
    src, tgt = keypoint_pair(2, dtype=torch.float32)
    phi = FAMILIES[name]().fit(src, tgt)
    x = grid(2, n=6, dtype=torch.float32).reshape(3, 12, 2)
    y = phi(x)
    assert y.shape == x.shape and y.dtype == torch.float32
    assert phi.jacobian(x).shape == (3, 12, 2, 2)
    mean, var = phi.predict(x)
    assert mean.shape == var.shape == x.shape
    assert phi.sample(x, 2).shape == (2, 3, 12, 2)
    # float32 and float64 fits agree where the keypoints are (hyper-parameters may differ far away)
    inside = grid(2, lo=0.0, hi=1.0, n=6)
    ref = FAMILIES[name]().fit(src.double(), tgt.double())
    torch.testing.assert_close(phi(inside.float()).double(), ref(inside), atol=1e-2, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("name", FAMILIES)
def test_cuda_follows_data(name):
    src, tgt = keypoint_pair(2)
    phi = FAMILIES[name]().fit(src.cuda(), tgt.cuda())
    x = grid(2, n=5)
    y = phi(x.cuda())
    assert y.device.type == "cuda"
    cpu = FAMILIES[name]().fit(src, tgt)
    torch.testing.assert_close(y.cpu(), cpu(x), atol=1e-4, rtol=0)


# ------------------------------------------------------------------ property-based
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), n=st.integers(3, 40), d=st.sampled_from([2, 3]), amp=st.floats(0.0, 0.3))
def test_ilwr_is_a_diffeomorphism_for_random_keypoints(seed, n, d, amp):
    g = torch.Generator().manual_seed(seed)
    src = torch.rand(n, d, generator=g, dtype=torch.float64)
    tgt = src + amp * torch.randn(n, d, generator=g, dtype=torch.float64)
    phi = ILWRMap().fit(src, tgt)
    x = grid(d, n=7 if d == 3 else 10)
    assert torch.linalg.det(phi.jacobian(x)).min() > 0
    torch.testing.assert_close(phi.inverse(phi(x)), x, atol=1e-6, rtol=0)
    # the translations improve on the rigid alignment they start from
    rigid = AffineMap("rigid").fit(src, tgt)
    assert (phi(src) - tgt).square().sum() <= (rigid(src) - tgt).square().sum() + 1e-12


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), angle=st.floats(-3.1, 3.1), d=st.sampled_from([2, 3]), scale=st.floats(0.2, 5.0))
def test_umeyama_recovers_random_similarity(seed, angle, d, scale):
    g = torch.Generator().manual_seed(seed)
    src = torch.rand(6, d, generator=g, dtype=torch.float64)
    r = rotation(d, angle)
    tgt = scale * src @ r.T + torch.randn(d, generator=g, dtype=torch.float64)
    phi = AffineMap("similarity").fit(src, tgt)
    torch.testing.assert_close(phi.A[0], scale * r, atol=1e-8, rtol=0)
    assert torch.linalg.det(AffineMap("rigid").fit(src, tgt).A[0]) > 0  # reflection-safe


def test_kabsch_never_returns_a_reflection():
    src, _ = keypoint_pair(2)
    mirrored = src * torch.tensor([-1.0, 1.0], dtype=src.dtype)
    phi = AffineMap("rigid").fit(src, mirrored)
    torch.testing.assert_close(torch.linalg.det(phi.A[0]), torch.tensor(1.0, dtype=src.dtype))


def test_full_affine_recovers_shear():
    src, _ = keypoint_pair(2)
    a = torch.tensor([[1.2, 0.4], [-0.1, 0.8]], dtype=src.dtype)
    phi = AffineMap("affine").fit(src, src @ a.T + 1.0)
    torch.testing.assert_close(phi.A[0], a)
    x = grid(2, n=5)
    torch.testing.assert_close(phi.inverse(phi(x)), x)


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("name", FAMILIES)
def test_bad_input_raises_clear_errors(name):
    src, tgt = keypoint_pair(2)
    make = FAMILIES[name]
    with pytest.raises(ValueError, match="correspond one to one"):
        make().fit(src, tgt[:-1])
    with pytest.raises(ValueError, match="NaN or inf"):
        bad = tgt.clone()
        bad[3, 1] = float("nan")
        make().fit(src, bad)
    with pytest.raises(ValueError, match="NaN or inf"):
        bad = src.clone()
        bad[0, 0] = float("inf")
        make().fit(bad, tgt)
    with pytest.raises(ValueError, match="too few keypoints"):
        make().fit(src[:1], tgt[:1])
    with pytest.raises(ValueError, match="duplicate source keypoints"):
        dup = src.clone()
        dup[5] = dup[2]
        make().fit(dup, tgt)
    with pytest.raises(ValueError, match=r"shape \[N, D\]|shape \[\.\.\., N, D\]"):
        make().fit(src[0], tgt[0])
    phi = make()
    with pytest.raises(RuntimeError, match="not fitted"):
        phi(src)
    phi.fit(src, tgt)
    with pytest.raises(ValueError, match=r"shape \[\.\.\., 2\]"):
        phi(torch.zeros(4, 3, dtype=src.dtype))
    with pytest.raises(ValueError, match="NaN or inf"):
        phi(torch.full((1, 2), float("nan"), dtype=src.dtype))


def test_degenerate_configurations():
    line = torch.stack([torch.linspace(0, 1, 5), torch.zeros(5)], -1).double()
    with pytest.raises(ValueError, match="collinear"):
        AffineMap("affine").fit(line, line + 1)
    with pytest.raises(ValueError, match="coincide"):
        AffineMap("rigid").fit(torch.zeros(3, 2), torch.ones(3, 2))
    with pytest.raises(ValueError, match="one keypoint set at a time"):
        GPMap().fit(torch.rand(2, 5, 2), torch.rand(2, 5, 2))
    with pytest.raises(ValueError, match="beta"):
        ILWRMap(beta=1.5)
    with pytest.raises(ValueError, match="unknown affine kind"):
        AffineMap("shear")


def test_flow_log_det_matches_jacobian():
    src, tgt = keypoint_pair(2)
    phi = FlowMap(steps=50).fit(src, tgt)
    x = grid(2, n=6)
    torch.testing.assert_close(phi.log_det_jacobian(x), torch.linalg.slogdet(phi.jacobian(x)).logabsdet, atol=1e-8, rtol=0)
