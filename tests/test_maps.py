"""Properties every transportation map family must have (issue 2, section 5)."""

import functools

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from kpflow.geometry.alignment import fit_affine
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


def test_gp_noise_knob_smooths_the_keypoints_by_some_percent_of_the_deformation():
    src, tgt = keypoint_pair(2)
    base = GPMap().alignment.fit(src, tgt)(src)
    deformation = (tgt - base).norm(dim=-1).max()
    err = (GPMap(noise=1e-2).fit(src, tgt)(src) - tgt).norm(dim=-1).max()  # noise 1 % of the residuals' mean square
    assert 1e-3 < err < 0.1 * deformation


@pytest.mark.parametrize("name", ["ilwr", "gp", "flow", "mlp"])
@pytest.mark.parametrize("kind", ["rigid", "similarity"])
def test_recovers_rigid_and_similarity_motion(name, kind):
    src, _ = keypoint_pair(3)
    scale = 1.0 if kind == "rigid" else 1.7
    tgt = scale * src @ rotation(3, 2.0).T + torch.tensor([0.5, -1.0, 2.0], dtype=src.dtype)
    phi = {
        "ilwr": ILWRMap,
        "gp": GPMap,
        "flow": functools.partial(FlowMap, steps=50),
        "mlp": functools.partial(MLPMap, steps=50),
    }[name](alignment=kind).fit(src, tgt)
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
    # the Jacobian's variance follows: far away it is the prior, 3 s^2 / l^2 for the default Matern 3/2 kernel
    jv = phi.jacobian_variance(far)
    torch.testing.assert_close(jv, (3 * phi.gp.outputscale / phi.gp.lengthscale**2).expand(1, 2, 2), rtol=1e-3, atol=0)


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
@settings(max_examples=25)
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


@settings(max_examples=30)
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


def test_weighted_rigid_fit_is_the_planar_closed_form():
    """2-D weighted Kabsch in closed form: with weighted centroids and centred x_i, y_i,
    theta = atan2(sum_i w_i x_i cross y_i, sum_i w_i x_i . y_i), R = R(theta), t = mean_w(T) - R mean_w(S)."""
    g = torch.Generator().manual_seed(3)
    src, tgt = torch.rand(7, 2, generator=g, dtype=torch.float64), torch.rand(7, 2, generator=g, dtype=torch.float64)
    w = torch.rand(7, generator=g, dtype=torch.float64) + 0.1
    ms, mt = (w[:, None] * src).sum(0) / w.sum(), (w[:, None] * tgt).sum(0) / w.sum()
    x, y = src - ms, tgt - mt
    theta = torch.atan2((w * (x[:, 0] * y[:, 1] - x[:, 1] * y[:, 0])).sum(), (w[:, None] * x * y).sum())
    r = torch.stack([torch.stack([theta.cos(), -theta.sin()]), torch.stack([theta.sin(), theta.cos()])])
    a, t = fit_affine(src[None], tgt[None], "rigid", w)
    torch.testing.assert_close(a[0], r, atol=1e-12, rtol=0)
    torch.testing.assert_close(t[0], mt - r @ ms, atol=1e-12, rtol=0)


@pytest.mark.parametrize("scale", [1e-150, 1e-3, 1.0, 512.0, 1e150])
def test_planar_rigid_fit_recovers_a_turn_at_any_scale(scale):
    """The 2-D rigid fit's closed form sums in units of a power of two near the spread: no under- or overflow."""
    src, _ = keypoint_pair(2)
    r = rotation(2, 2.5)
    a, t = fit_affine(scale * src[None], scale * (src @ r.T + 0.25)[None], "rigid")
    torch.testing.assert_close(a[0], r, atol=1e-12, rtol=0)
    torch.testing.assert_close(t[0] / scale, torch.full((2,), 0.25, dtype=src.dtype), atol=1e-12, rtol=0)


@pytest.mark.parametrize("kind", ["rigid", "similarity", "affine", "translation"])
@pytest.mark.parametrize("d", [2, 3])
def test_integer_weights_count_points_and_zero_weights_drop_them(kind, d):
    g = torch.Generator().manual_seed(d)
    src, tgt = torch.rand(2, 8, d, generator=g, dtype=torch.float64)
    counts = torch.tensor([1, 3, 2, 1, 0, 2, 1, 4], dtype=torch.float64)
    repeated = counts.long()
    want = fit_affine(src.repeat_interleave(repeated, 0)[None], tgt.repeat_interleave(repeated, 0)[None], kind)
    for weights in (counts, 0.25 * counts[None]):  # [N] or [B, N]; only their ratios count
        for got, expected in zip(fit_affine(src[None], tgt[None], kind, weights), want):
            torch.testing.assert_close(got, expected, atol=1e-12, rtol=0)


def test_fit_affine_refuses_weights_that_weigh_nothing():
    src, tgt = keypoint_pair(2)
    for bad in (torch.zeros(len(src)), torch.full((len(src),), -1.0), torch.full((len(src),), float("nan"))):
        with pytest.raises(ValueError, match="point weights must be finite and >= 0"):
            fit_affine(src[None], tgt[None], "rigid", bad)
    one = torch.zeros(len(src), dtype=src.dtype)
    one[0] = 1.0
    with pytest.raises(ValueError, match="keypoints of positive weight coincide"):
        fit_affine(src[None], tgt[None], "rigid", one)


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
    torch.testing.assert_close(
        phi.log_det_jacobian(x), torch.linalg.slogdet(phi.jacobian(x)).logabsdet, atol=1e-8, rtol=0
    )


# ------------------------------------------------------------------ bad input: dtypes, scale, hyper-parameters
@pytest.fixture(scope="module")
def fitted():
    """One fitted map of every family (float64), shared by the query tests below."""
    src, tgt = keypoint_pair(2)
    return {name: make().fit(src, tgt) for name, make in FAMILIES.items()}


UNSUPPORTED = [torch.float16, torch.bfloat16, torch.complex64, torch.complex128]


@pytest.mark.parametrize("dtype", UNSUPPORTED, ids=str)
@pytest.mark.parametrize("name", FAMILIES)
def test_half_precision_and_complex_inputs_raise(fitted, name, dtype):
    src, tgt = keypoint_pair(2)
    msg = rf"has (complex )?dtype {dtype}.*float32 or float64"
    with pytest.raises(ValueError, match="source " + msg):
        FAMILIES[name]().fit(src.to(dtype), tgt)
    with pytest.raises(ValueError, match="target " + msg):
        FAMILIES[name]().fit(src, tgt.to(dtype))
    phi = fitted[name]
    x = grid(2, n=4).to(dtype)
    for method in (phi, phi.jacobian, phi.predict, lambda q: phi.sample(q, 2)):
        with pytest.raises(ValueError, match="x " + msg):
            method(x)
    with pytest.raises(ValueError, match="y " + msg):
        phi.inverse(x)


def test_unsupported_dtypes_from_numpy_and_python_raise():
    src, tgt = keypoint_pair(2)
    with pytest.raises(ValueError, match="source has dtype torch.float16.*float32 or float64"):
        AffineMap().fit(src.numpy().astype(np.float16), tgt)
    phi = AffineMap().fit(src, tgt)
    with pytest.raises(ValueError, match="x has complex dtype torch.complex.*float32 or float64"):
        phi([[1 + 2j, 0.5]])


def test_integer_inputs_are_converted_to_float():
    """Integers are converted by design: a fit to the default dtype, a query to the map's dtype."""
    src = torch.tensor([[0, 0], [4, 0], [0, 3], [5, 5]])
    phi = AffineMap("affine").fit(src, src * 2 + 1)
    assert phi.A.dtype == torch.get_default_dtype()
    torch.testing.assert_close(phi(torch.tensor([[1, 2]])), torch.tensor([[3.0, 5.0]]))
    ref = AffineMap().fit(*keypoint_pair(2))
    y = ref(torch.tensor([[1, 2]]))
    assert y.dtype == torch.float64
    torch.testing.assert_close(y, ref(torch.tensor([[1.0, 2.0]], dtype=torch.float64)), atol=0, rtol=0)


SCALE_FAMILIES = {
    "rigid": lambda: AffineMap("rigid"),
    "similarity": lambda: AffineMap("similarity"),
    "affine": lambda: AffineMap("affine"),
    "translation": lambda: AffineMap("translation"),
    "ilwr": lambda: ILWRMap(),
    "gp": lambda: GPMap(),
    "flow": lambda: FlowMap(steps=100),
    "mlp": lambda: MLPMap(steps=100),
}
NEURAL = ("flow", "mlp")  # L-BFGS on different rounding: equal fits only up to the optimiser's tolerance


@pytest.mark.parametrize("scale", [1e-5, 1e-12, 1e5])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=str)
@pytest.mark.parametrize("name", SCALE_FAMILIES)
def test_small_and_large_keypoint_sets_fit_like_unit_ones(name, dtype, scale):
    """Coincidence (and every other threshold) is relative to the keypoints' own magnitude: a well-shaped set
    scaled by ``scale`` fits, and the map is the unit-scale map scaled (phi_s(s x) = s phi_1(x))."""
    src, tgt = keypoint_pair(2, dtype=dtype)
    ref = SCALE_FAMILIES[name]().fit(src, tgt)
    phi = SCALE_FAMILIES[name]().fit(src * scale, tgt * scale)
    f32 = dtype == torch.float32
    slack = (1e-2 if f32 else 1e-4) if name in NEURAL else (1e-3 if f32 else 1e-8)
    err_ref = (ref(src) - tgt).abs().max()
    err = (phi(src * scale) - tgt * scale).abs().max() / scale  # phi(S) ~= T relative to the scale
    assert err <= err_ref + slack, (err, err_ref)
    x = grid(2, n=6, dtype=dtype)
    if name not in NEURAL:
        torch.testing.assert_close(phi(x * scale) / scale, ref(x), atol=2e-4 if f32 else 1e-8, rtol=0)
    if name in ("rigid", "similarity", "affine", "translation", "ilwr", "flow"):  # exact inverses
        back = phi.inverse(phi(x * scale)) / scale
        torch.testing.assert_close(back, x, atol=1e-5 if f32 else 1e-9, rtol=0)


def _ulp_steps(p: torch.Tensor, k: int) -> torch.Tensor:
    for _ in range(k):
        p = torch.nextafter(p, torch.full_like(p, float("inf")))
    return p


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=str)
@pytest.mark.parametrize("name", ["rigid", "similarity", "affine", "ilwr", "gp"])
def test_truly_coincident_keypoints_still_raise(name, dtype):
    p = torch.tensor([0.3, 0.7], dtype=dtype)
    cases = {
        "all equal": p.expand(4, 2).clone(),
        "all zero": torch.zeros(4, 2, dtype=dtype),
        "equal up to a few ulps": torch.stack([_ulp_steps(p, k) for k in range(4)])
        * torch.tensor([1.0, -1.0], dtype=dtype),
        "tiny and equal up to a few ulps": torch.stack([_ulp_steps(p * 1e-6, k) for k in (0, 1, 3, 4)]),
    }
    for case, src in cases.items():
        with pytest.raises(ValueError, match="all source keypoints coincide.*within .* resolution"):
            SCALE_FAMILIES[name]().fit(src, src + 1.0)
            pytest.fail(case)


def test_duplicates_are_found_among_many_keypoints_far_from_the_origin():
    """cdist's matrix-product form (N > 25) is off by ~sqrt(eps) |x|: duplicates must be found regardless."""
    for dtype in (torch.float32, torch.float64):
        g = torch.Generator().manual_seed(0)
        for j in range(1, 60, 3):
            src = torch.rand(60, 2, generator=g, dtype=dtype) * 3 + 1234.5
            src[j] = src[0]
            with pytest.raises(ValueError, match=f"duplicate source keypoints 0 and {j} coincide"):
                AffineMap().fit(src, torch.rand(60, 2, generator=g, dtype=dtype))


@pytest.mark.parametrize(
    "arg, value",
    [
        ("lengthscale", -1),
        ("lengthscale", 0.0),
        ("lengthscale", float("nan")),
        ("lengthscale", float("inf")),
        ("noise", -1e-3),
        ("noise", 0),
        ("min_noise", -1.0),
        ("min_noise", 0.0),
        ("iters", -1),
        ("iters", 2.5),
        ("max_sample_bytes", 0),
        ("max_sample_bytes", -5),
    ],
)
def test_gp_hyperparameters_are_checked_at_construction(arg, value):
    with pytest.raises(
        ValueError, match=rf"^{arg} must be (a positive finite number|an integer >= 0).*; got {value!r}"
    ):
        GPMap(**{arg: value})


def test_gp_regressor_checks_outputscale():
    from kpflow.maps.gp_regression import GPRegressor

    with pytest.raises(ValueError, match=r"outputscale must be a positive finite number; got -2\.0"):
        GPRegressor(outputscale=-2.0)


def test_gp_sample_refuses_a_joint_covariance_over_the_memory_limit():
    from kpflow.maps import gp_regression

    src, tgt = keypoint_pair(2)
    phi = GPMap(max_sample_bytes=10_000).fit(src, tgt)
    x = grid(2, n=6)  # 36 points: 2 x 36 x 36 float64 = 20736 B > 10000 B
    msg = (
        r"sample\(\) at 36 points needs a joint posterior covariance of 2 x 36 x 36 torch.float64 \(20\.\d KiB.*"
        r"over the limit of 9\.77 KiB \(max_sample_bytes\): the cost is quadratic in the number of points\. "
        r"Sample fewer points, or in chunks.*use predict\(\)"
    )
    with pytest.raises(ValueError, match=msg):
        phi.sample(x, 3)
    assert phi.sample(x[:25], 3).shape == (3, 25, 2)  # 2 x 25 x 25 x 8 = 10000 B: within the limit
    mean, var = phi.predict(x)  # the suggested way out works at any size
    assert mean.shape == var.shape == x.shape
    # the default limit (1 GiB) refuses the reported case, 2e4 points (6.4 GB), before allocating anything
    assert gp_regression.MAX_SAMPLE_BYTES == 1 << 30
    with pytest.raises(ValueError, match=r"at 20000 points .*\(5\.96 GiB.*limit of 1 GiB"):
        GPMap().fit(src, tgt).sample(torch.zeros(20_000, 2, dtype=src.dtype), 1)


@pytest.mark.parametrize("name", FAMILIES)
def test_outputs_carry_no_autograd_graph_unless_the_query_requires_grad(fitted, name):
    """Like every family, GPMap freezes its fitted parameters: outputs for a plain query are plain tensors
    (no graph kept alive: memory), while a query that requires grad still gets gradients."""
    phi = fitted[name]
    assert not any(p.requires_grad for p in phi.parameters())
    x = grid(2, n=5)
    mean, var = phi.predict(x)
    for label, out in {
        "forward": phi(x),
        "inverse": phi.inverse(x),
        "jacobian": phi.jacobian(x),
        "mean": mean,
        "variance": var,
        "sample": phi.sample(x, 2),
    }.items():
        assert out.requires_grad is False and out.grad_fn is None, label
    xg = x.clone().requires_grad_(True)
    y = phi(xg)
    assert y.requires_grad and phi.predict(xg)[0].requires_grad
    (grad,) = torch.autograd.grad(y.sum(), xg)
    torch.testing.assert_close(grad, phi.jacobian(x).sum(-2), atol=1e-8, rtol=1e-8)


def test_gp_default_length_scale_is_in_units_of_the_keypoints_diameter():
    src, tgt = keypoint_pair(2)
    phi = GPMap().fit(src, tgt)
    diameter = torch.pdist(src).max()
    torch.testing.assert_close(phi.gp.lengthscale, 0.8 * diameter, rtol=1e-6, atol=0)  # through softplus: ~1e-8
    spread = GPMap(lengthscale=2.0, lengthscale_unit="spread").fit(src, tgt)
    rms = (src - src.mean(0)).square().sum(-1).mean().sqrt()
    torch.testing.assert_close(spread.gp.lengthscale, 2.0 * rms, rtol=1e-6, atol=0)
    scaled = GPMap().fit(7.0 * src, 7.0 * tgt)  # the keypoints' own units: scaling them scales the map
    x = grid(2, n=5)
    torch.testing.assert_close(scaled(7.0 * x), 7.0 * phi(x), rtol=1e-6, atol=1e-9)
    with pytest.raises(ValueError, match="lengthscale_unit"):
        GPMap(lengthscale_unit="pixels")
