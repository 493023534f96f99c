"""The GP's kernel, mean and likelihood injected as gpytorch modules (kpflow/maps/gp_regression.py): every kernel
recovers a known function, length-scale bounds in keypoint units hold, restarts never lose likelihood, one
template serves many fits, and the Jacobian's variance matches each kernel's closed-form prior."""

import math

import gpytorch
import pytest
import torch

from kpflow.maps import GPMap
from kpflow.maps.gp_regression import GPRegressor, derivative_prior
from tests.helpers import keypoint_pair

K = gpytorch.kernels
KERNELS = {
    "rbf": lambda: K.RBFKernel(),
    "matern12": lambda: K.MaternKernel(nu=0.5),
    "matern32": lambda: K.MaternKernel(nu=1.5),
    "matern52": lambda: K.MaternKernel(nu=2.5),
    "rbf+matern32": lambda: K.RBFKernel() + K.MaternKernel(nu=1.5),
    "rbf*periodic": lambda: K.RBFKernel() * K.PeriodicKernel(),
}


def smooth_data(n: int = 40, seed: int = 0):
    """A known smooth function of the plane, two outputs, sampled at n points."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 2, generator=g, dtype=torch.float64) * 4 - 2
    f = lambda z: torch.stack([torch.sin(z[:, 0]) * torch.cos(0.5 * z[:, 1]), 0.3 * z[:, 0] * z[:, 1]], -1)  # noqa: E731
    return x, f(x), f


@pytest.mark.parametrize("name", KERNELS)
def test_every_kernel_recovers_a_known_function(name):
    x, y, f = smooth_data()
    gp = GPRegressor(kernel=KERNELS[name](), iters=50).fit(x, y)
    test = torch.rand(200, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 3 - 1.5
    error = (gp.mean(test) - f(test)).abs().max()
    assert error < (0.12 if name == "matern12" else 0.05), error  # the rough Matern 1/2 interpolates less well


def test_lengthscale_bounds_are_in_keypoint_units_and_hold():
    x, y, _ = smooth_data()
    free = GPRegressor(iters=50).fit(x, y).lengthscale
    for scale in (1.0, 100.0):  # the same bounds relative to the data: the same fit in standardised units
        low, high = 2.0 * scale * float(free), 4.0 * scale * float(free)
        gp = GPRegressor(iters=50, lengthscale_bounds=(low, high)).fit(scale * x, y)
        assert low * (1 - 1e-6) <= float(gp.lengthscale) <= high * (1 + 1e-6)  # the Interval transform, to rounding
    assert float(gp.lengthscale) == pytest.approx(low, rel=1e-3)  # the data want a shorter one: it sits at the bound
    with pytest.raises(ValueError, match="lengthscale_bounds must be"):
        GPRegressor(lengthscale_bounds=(5.0, 1.0))


def test_restarts_never_lose_likelihood_and_are_deterministic():
    x, y, _ = smooth_data(seed=3)

    def nll(gp):
        gp.model.train(), gp.likelihood.train()
        mll = gpytorch.mlls.ExactMarginalLogLikelihood(gp.likelihood, gp.model)
        with torch.no_grad():
            return float(-mll(gp.model(*gp.model.train_inputs), gp.model.train_targets).sum())

    one = GPRegressor(iters=4, lengthscale=30.0).fit(x, y)  # a poor start
    many = GPRegressor(iters=4, lengthscale=30.0, restarts=4).fit(x, y)
    assert nll(many) <= nll(one) + 1e-9
    again = GPRegressor(iters=4, lengthscale=30.0, restarts=4).fit(x, y)
    assert torch.equal(many.lengthscale, again.lengthscale)


def test_one_template_serves_many_fits_untouched():
    kernel = K.MaternKernel(nu=2.5)
    before = kernel.lengthscale.clone()
    make = lambda: GPMap(kernel=kernel, mean=gpytorch.means.ZeroMean())  # noqa: E731  (what a Hydra partial does)
    a = make().fit(*keypoint_pair(2, seed=0))
    b = make().fit(*keypoint_pair(2, seed=5))
    assert torch.equal(kernel.lengthscale, before) and a.gp.model.covar_module is not b.gp.model.covar_module
    assert not torch.equal(a.gp.lengthscale, b.gp.lengthscale)


@pytest.mark.parametrize(("name", "factor"), [("rbf", 1.0), ("matern32", 3.0), ("matern52", 5.0 / 3.0)])
def test_jacobian_variance_far_away_is_the_kernels_prior(name, factor):
    """Far from every keypoint var(d phi_i / d x_j) is the prior -k''(0) = factor * s^2 / l^2 (module docstring)."""
    src, tgt = keypoint_pair(2)
    phi = GPMap(kernel=KERNELS[name]()).fit(src, tgt)
    far = torch.tensor([[40.0, -30.0]], dtype=src.dtype)
    expected = factor * phi.gp.outputscale / phi.gp.lengthscale**2
    torch.testing.assert_close(phi.jacobian_variance(far), expected.expand(1, 2, 2), rtol=1e-3, atol=0)


def test_jacobian_variance_is_the_variance_of_the_sampled_slope():
    """A finite-difference slope of joint posterior samples has the variance jacobian_variance gives (Matern 5/2)."""
    src, tgt = keypoint_pair(2)
    phi = GPMap(kernel=K.MaternKernel(nu=2.5)).fit(src, tgt)
    x = torch.tensor([[0.5, 1.4]], dtype=src.dtype)
    h = 1e-3
    pts = torch.cat([x - torch.tensor([[h, 0.0]], dtype=x.dtype), x + torch.tensor([[h, 0.0]], dtype=x.dtype)])
    s = phi.sample(pts, 4000, generator=torch.Generator().manual_seed(0))
    slope = (s[:, 1, 0] - s[:, 0, 0]) / (2 * h)  # d phi_0 / d x_0 of each sample
    assert float(slope.var()) == pytest.approx(float(phi.jacobian_variance(x)[0, 0, 0]), rel=0.1)


def test_kernels_without_a_finite_jacobian_variance_say_so():
    with pytest.raises(ValueError, match="not mean-square differentiable"):
        derivative_prior(K.ScaleKernel(K.MaternKernel(nu=0.5)))
    with pytest.raises(ValueError, match="RBF and Matern"):
        derivative_prior(K.RBFKernel() * K.PeriodicKernel())
    with pytest.raises(ValueError, match="kernel must be a gpytorch.kernels"):
        GPMap(kernel="rbf")
    with pytest.raises(ValueError, match="no length-scale"):
        GPMap(kernel=K.LinearKernel())
    assert math.isfinite(float(derivative_prior(K.ScaleKernel(K.RBFKernel() + K.MaternKernel(nu=2.5)))))
