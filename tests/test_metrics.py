import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from kpflow.eval.metrics import (
    band_coverage,
    discrete_frechet,
    dtw,
    final_position_error,
    rotation_angle_error,
)


def _reference(a, b, combine):
    """Plain-python DP over the full cost table (the textbook recursion)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    T, S = len(a), len(b)
    c = np.full((T, S), np.inf)
    for i in range(T):
        for j in range(S):
            d = np.linalg.norm(a[i] - b[j])
            if i == 0 and j == 0:
                c[i, j] = d
                continue
            prev = min(
                c[i - 1, j] if i > 0 else np.inf,
                c[i, j - 1] if j > 0 else np.inf,
                c[i - 1, j - 1] if i > 0 and j > 0 else np.inf,
            )
            c[i, j] = combine(d, prev)
    return c[-1, -1]


def _rot3(axis, angle):
    axis = torch.as_tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    K = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _rot2(angle):
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s], [s, c]], dtype=torch.float64)


# ---- Fréchet / DTW --------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_identical_curves_are_at_distance_zero(dtype):
    a = torch.randn(30, 3, dtype=dtype, generator=torch.Generator().manual_seed(0))
    assert discrete_frechet(a, a).item() == 0.0
    assert dtw(a, a).item() == 0.0
    assert final_position_error(a, a).item() == 0.0
    assert discrete_frechet(a, a).dtype == dtype and dtw(a, a).dtype == dtype


def test_translate_perpendicular_to_a_line():
    T, d = 25, 0.7
    a = torch.stack([torch.linspace(0, 3, T, dtype=torch.float64), torch.zeros(T, dtype=torch.float64)], 1)
    b = a + torch.tensor([0.0, d], dtype=torch.float64)
    assert discrete_frechet(a, b).item() == pytest.approx(d, abs=1e-12)
    assert dtw(a, b).item() == pytest.approx(T * d, abs=1e-10)
    assert final_position_error(a, b).item() == pytest.approx(d, abs=1e-12)


def test_frechet_of_any_translate_is_the_shift():
    g = torch.Generator().manual_seed(1)
    a = torch.randn(40, 2, dtype=torch.float64, generator=g).cumsum(0)
    shift = torch.tensor([0.3, -0.4], dtype=torch.float64)
    assert discrete_frechet(a, a + shift).item() == pytest.approx(0.5, abs=1e-12)


def test_small_example_by_hand():
    # a = (0,0),(1,0),(2,0); b = (0,1),(2,1). Distances d[i,j]:
    #   [[1, sqrt5], [sqrt2, sqrt2], [sqrt5, 1]]
    # Fréchet table: [[1, sqrt5], [sqrt2, sqrt2], [sqrt5, sqrt2]]   -> sqrt2
    # DTW table:     [[1, 1+sqrt5], [1+sqrt2, 1+sqrt2], [1+sqrt2+sqrt5, 2+sqrt2]] -> 2+sqrt2
    a = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], dtype=torch.float64)
    b = torch.tensor([[0.0, 1.0], [2.0, 1.0]], dtype=torch.float64)
    assert discrete_frechet(a, b).item() == pytest.approx(math.sqrt(2))
    assert dtw(a, b).item() == pytest.approx(2 + math.sqrt(2))
    assert final_position_error(a, b).item() == pytest.approx(1.0)


def test_one_dimensional_example_by_hand():
    # Warping absorbs the repeated samples: DTW([0,1,2], [0,0,1,1,2]) = 0, Fréchet = 0.
    a = torch.tensor([[0.0], [1.0], [2.0]])
    b = torch.tensor([[0.0], [0.0], [1.0], [1.0], [2.0]])
    assert dtw(a, b).item() == 0.0
    assert discrete_frechet(a, b).item() == 0.0
    # A spike: c = [0, 5, 2]. The spike (5) must be coupled with a[1] (cost 4) or with
    # a[2] (cost 3, but then a[1] is coupled with c[0], cost 1): Fréchet = 3, DTW = 4.
    c = torch.tensor([[0.0], [5.0], [2.0]])
    assert discrete_frechet(a, c).item() == pytest.approx(3.0)
    assert dtw(a, c).item() == pytest.approx(4.0)


def test_single_point_curves():
    a = torch.tensor([[0.0, 0.0]])
    b = torch.tensor([[3.0, 4.0], [0.0, 0.0]])
    assert discrete_frechet(a, b).item() == pytest.approx(5.0)
    assert dtw(a, b).item() == pytest.approx(5.0)


def test_matches_reference_dp_on_random_curves():
    g = torch.Generator().manual_seed(2)
    for T, S in [(7, 7), (5, 11), (13, 3)]:
        a = torch.randn(T, 2, dtype=torch.float64, generator=g)
        b = torch.randn(S, 2, dtype=torch.float64, generator=g)
        assert discrete_frechet(a, b).item() == pytest.approx(_reference(a, b, max), rel=1e-12)
        assert dtw(a, b).item() == pytest.approx(_reference(a, b, lambda d, p: d + p), rel=1e-12)


def test_dtw_is_symmetric_and_batched():
    g = torch.Generator().manual_seed(3)
    a = torch.randn(4, 20, 3, generator=g, dtype=torch.float64)
    b = torch.randn(4, 15, 3, generator=g, dtype=torch.float64)
    d_ab, d_ba = dtw(a, b), dtw(b, a)
    assert d_ab.shape == (4,)
    torch.testing.assert_close(d_ab, d_ba)
    torch.testing.assert_close(d_ab[2], dtw(a[2], b[2]))
    torch.testing.assert_close(discrete_frechet(a, b)[1], discrete_frechet(a[1], b[1]))
    # A single curve broadcasts against a batch.
    torch.testing.assert_close(dtw(a, b[0])[3], dtw(a[3], b[0]))


def test_frechet_bounded_by_max_pointwise_distance():
    g = torch.Generator().manual_seed(4)
    a = torch.randn(50, 2, generator=g, dtype=torch.float64)
    b = torch.randn(50, 2, generator=g, dtype=torch.float64)
    assert discrete_frechet(a, b) <= (a - b).norm(dim=-1).max() + 1e-12


def test_numpy_input_and_gradients():
    a = np.random.default_rng(0).normal(size=(10, 2))
    b = np.random.default_rng(1).normal(size=(12, 2))
    assert discrete_frechet(a, b).dtype == torch.float64
    at = torch.as_tensor(a).requires_grad_()
    dtw(at, b).backward()
    assert torch.isfinite(at.grad).all() and at.grad.abs().sum() > 0


def test_bad_input_raises():
    a = torch.zeros(5, 2)
    with pytest.raises(ValueError, match="same point dimension"):
        dtw(a, torch.zeros(5, 3))
    with pytest.raises(ValueError, match="NaN"):
        discrete_frechet(a, torch.full((4, 2), float("nan")))
    with pytest.raises(ValueError, match="curve"):
        discrete_frechet(torch.zeros(5), a)
    with pytest.raises(ValueError, match="at least one point"):
        dtw(torch.zeros(0, 2), a)


@settings(max_examples=60)
@given(
    st.lists(st.tuples(st.floats(-10, 10), st.floats(-10, 10)), min_size=1, max_size=12),
    st.lists(st.tuples(st.floats(-10, 10), st.floats(-10, 10)), min_size=1, max_size=12),
)
def test_frechet_properties(pa, pb):
    a = torch.tensor(pa, dtype=torch.float64)
    b = torch.tensor(pb, dtype=torch.float64)
    f_ab, f_ba = discrete_frechet(a, b), discrete_frechet(b, a)
    assert f_ab.item() == pytest.approx(f_ba.item(), abs=1e-12)
    assert f_ab >= (a[0] - b[0]).norm() - 1e-12
    assert f_ab >= (a[-1] - b[-1]).norm() - 1e-12
    # The DTW-optimal coupling's largest distance is >= Fréchet, and its sum >= its largest.
    assert dtw(a, b) >= f_ab - 1e-9
    assert dtw(a, b).item() == pytest.approx(dtw(b, a).item(), abs=1e-9)
    if len(a) == len(b):
        assert f_ab <= (a - b).norm(dim=-1).max() + 1e-12


# ---- rotations ------------------------------------------------------------------------


@pytest.mark.parametrize("angle", [0.0, 1e-4, 0.3, 1.5, 2.9, math.pi])
def test_rotation_error_2d(angle):
    base = _rot2(0.7)
    assert rotation_angle_error(base, base @ _rot2(angle)).item() == pytest.approx(angle, abs=1e-12)
    assert rotation_angle_error(base, base @ _rot2(-angle)).item() == pytest.approx(angle, abs=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-5, 0.3, 1.5, 2.9, math.pi - 1e-6, math.pi])
def test_rotation_error_3d(angle):
    base = _rot3([1.0, 2.0, -0.5], 0.9)
    R = base @ _rot3([0.2, -1.0, 0.4], angle)
    assert rotation_angle_error(base, R).item() == pytest.approx(angle, abs=1e-9)
    assert rotation_angle_error(R, base).item() == pytest.approx(angle, abs=1e-9)


def test_rotation_error_batched_float32():
    angles = torch.tensor([0.1, 0.5, 2.0])
    Rb = torch.stack([_rot3([0, 0, 1], a.item()) for a in angles]).float()
    Ra = torch.eye(3).expand(3, 3, 3)
    err = rotation_angle_error(Ra, Rb)
    assert err.dtype == torch.float32 and err.shape == (3,)
    torch.testing.assert_close(err, angles, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="D = 2 or 3"):
        rotation_angle_error(torch.eye(4), torch.eye(4))


# ---- band coverage --------------------------------------------------------------------


def test_band_coverage_constructed():
    T = 10
    mean = torch.zeros(T, 2)
    std = torch.ones(T, 2)
    truth = torch.zeros(T, 2)
    truth[:3, 0] = 2.5  # outside the 2-sigma band in x
    truth[3:5, 1] = -1.9  # inside
    truth[5, :] = 2.0  # on the boundary: inside
    assert band_coverage(mean, std, truth, k=2.0).item() == pytest.approx(0.7)
    assert band_coverage(mean, std, truth, k=3.0).item() == pytest.approx(1.0)
    # Per-point isotropic std [T].
    iso = torch.ones(T)
    iso[:3] = 1.5
    assert band_coverage(mean, iso, truth, k=2.0).item() == pytest.approx(1.0)
    # One coordinate outside is enough to be outside.
    std2 = std.clone()
    std2[6:, 1] = 0.0
    truth2 = truth.clone()
    truth2[6:, 1] = 1e-3
    assert band_coverage(mean, std2, truth2).item() == pytest.approx(0.3)


def test_band_coverage_bad_input():
    with pytest.raises(ValueError, match="std must have shape"):
        band_coverage(torch.zeros(5, 2), torch.ones(4), torch.zeros(5, 2))
    with pytest.raises(ValueError, match="non-negative"):
        band_coverage(torch.zeros(5, 2), -torch.ones(5), torch.zeros(5, 2))
    with pytest.raises(ValueError, match="truth"):
        band_coverage(torch.zeros(5, 2), torch.ones(5), torch.zeros(4, 2))
