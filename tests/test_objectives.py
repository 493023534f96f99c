"""The generative objectives in closed form: I-CFM and OT-CFM interpolants and targets, DDPM forward noising against
the squared-cosine schedule, one DDIM step on a one-point dataset; and the observation history of K-CFM."""

import math

import numpy as np
import pytest
import torch

from kpflow.policies.objectives import DDPM, ICFM, OBJECTIVES, OTCFM, build_objective
from kpflow.policies.objectives.icfm import euler


def _data(b=6, h=8, a=2, seed=0):
    return torch.randn(b, h, a, generator=torch.Generator().manual_seed(seed))


def test_icfm_interpolant_and_target_are_the_straight_path():
    x1 = _data()
    g = torch.Generator().manual_seed(3)
    target = ICFM().training_target(x1, generator=g)
    # the draw order: x0 ~ N(0, I) first, then t ~ U(0, 1)
    g = torch.Generator().manual_seed(3)
    x0, t = torch.randn(x1.shape, generator=g), torch.rand(len(x1), generator=g)
    torch.testing.assert_close(target.t, t)
    torch.testing.assert_close(target.x_t, t[:, None, None] * x1 + (1 - t[:, None, None]) * x0)
    torch.testing.assert_close(target.target, x1 - x0)
    assert target.index.tolist() == list(range(len(x1)))
    # u_t is d/dt x_t: the path is a line, so a finite difference in t is exact
    h = 1e-3
    path = lambda s: s * x1.double() + (1 - s) * x0.double()  # noqa: E731
    torch.testing.assert_close((path(0.3 + h) - path(0.3 - h)) / (2 * h), target.target.double(), atol=1e-6, rtol=1e-6)


def test_euler_integrates_the_exact_field_of_a_one_point_dataset_in_one_step():
    # for data = {x*}, the I-CFM field is v(x, t) = (x* - x) / (1 - t): one Euler step from t = 0 lands on x*
    star = torch.tensor([[[0.3, -0.7]] * 4])
    out = euler(lambda x, t: (star - x) / (1 - t[:, None, None]), torch.randn(1, 4, 2), steps=1)
    torch.testing.assert_close(out, star)


def test_otcfm_pairs_noise_with_its_nearest_data_row():
    # data rows far apart, noise rows = data rows + tiny offsets in shuffled order: the OT plan is that matching
    x1 = torch.arange(5.0)[:, None, None].expand(5, 3, 2) * 10.0
    perm = torch.tensor([3, 0, 4, 1, 2])
    objective = OTCFM(condition_weight=0.0)
    x0 = x1[perm] + 0.01
    paired, j = objective.pair(x0, x1, torch.Generator().manual_seed(0))
    torch.testing.assert_close(paired - 0.01, x1[j])  # every drawn pair is a matched pair
    target = objective.training_target(x1, generator=torch.Generator().manual_seed(0))
    x0_used = (target.x_t - target.t[:, None, None] * x1[target.index]) / (1 - target.t[:, None, None])
    torch.testing.assert_close(target.target, x1[target.index] - x0_used, atol=1e-4, rtol=1e-4)
    # reproducible with the generator
    again = objective.training_target(x1, generator=torch.Generator().manual_seed(0))
    assert torch.equal(again.index, target.index) and torch.equal(again.x_t, target.x_t)


def test_otcfm_straightens_the_coupling():
    x1 = _data(b=64, seed=1)
    x0 = torch.randn(x1.shape, generator=torch.Generator().manual_seed(2))
    paired, j = OTCFM(condition_weight=0.0).pair(x0, x1, torch.Generator().manual_seed(0))
    independent = (x1 - x0).square().sum((1, 2)).mean()
    assert (x1[j] - paired).square().sum((1, 2)).mean() < 0.8 * independent


def test_otcfm_pairs_only_within_a_condition():
    # two conditions far apart: every pair keeps noise of its own condition, so each condition's noise stays N(0, I)
    x1 = _data(b=64, seed=3)
    cond = torch.cat([torch.zeros(32, 4), torch.full((32, 4), 3.0)])
    x0 = torch.randn(x1.shape, generator=torch.Generator().manual_seed(4))
    objective = OTCFM(condition_weight=10.0)
    a = objective.plan.get_map(torch.cat([x0.flatten(1), 10**0.5 * cond], 1), torch.cat([x1.flatten(1), 10**0.5 * cond], 1))
    assert a[:32, 32:].sum() == 0 and a[32:, :32].sum() == 0  # no mass across conditions
    paired, j = objective.pair(x0, x1, torch.Generator().manual_seed(0), cond)
    source = torch.cdist(paired.flatten(1), x0.flatten(1)).argmin(1)  # which noise row each pair used
    assert torch.equal(source < 32, j < 32)
    # within a condition it still re-pairs: straighter than independent pairs
    assert (x1[j] - paired).square().sum((1, 2)).mean() < (x1 - x0).square().sum((1, 2)).mean()
    with pytest.raises(ValueError, match="condition_weight"):
        OTCFM(condition_weight=-1.0)


def test_ddpm_forward_noising_is_the_squared_cosine_schedule():
    T = 100
    objective = DDPM(train_steps=T)
    # Nichol & Dhariwal 2021 eq. 17 (betas capped at 0.999): alpha_bar(k) = prod_{i<=k} (1 - beta_i),
    # beta_i = 1 - f((i + 1) / T) / f(i / T), f(s) = cos((s + 0.008) / 1.008 * pi / 2)^2
    f = lambda s: math.cos((s + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
    betas = np.array([min(1 - f((i + 1) / T) / f(i / T), 0.999) for i in range(T)])
    np.testing.assert_allclose(objective.alphas_cumprod.numpy(), np.cumprod(1 - betas), rtol=1e-4)  # float32

    x1 = _data()
    target = objective.training_target(x1, generator=torch.Generator().manual_seed(5))
    g = torch.Generator().manual_seed(5)
    eps = torch.randn(x1.shape, generator=g)
    k = torch.randint(0, T, (len(x1),), generator=g)
    ab = torch.tensor(np.cumprod(1 - betas), dtype=torch.float32)[k][:, None, None]
    torch.testing.assert_close(target.x_t, ab.sqrt() * x1 + (1 - ab).sqrt() * eps, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(target.target, eps)
    torch.testing.assert_close(target.t, k.float() / T)


def test_one_ddim_step_on_a_one_point_dataset_returns_the_point():
    # for data = {x*}, the ideal noise predictor is eps(x_k) = (x_k - sqrt(ab_k) x*) / sqrt(1 - ab_k); one DDIM step
    # from k = T - 1 then gives x* exactly (|x*| < 1, so clipping does nothing)
    objective = DDPM(train_steps=100)
    ab = objective.alphas_cumprod
    star = torch.tensor([[[0.5, -0.25]] * 6])

    def ideal(x, t):
        a = ab[(t * 100).round().long()][:, None, None]
        return (x - a.sqrt() * star) / (1 - a).sqrt()

    noise = torch.randn(3, 6, 2, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(objective.sample(ideal, noise, steps=1), star.expand(3, 6, 2), atol=1e-3, rtol=0)  # float32: alpha_bar_99 = 2.4e-7
    torch.testing.assert_close(objective.sample(ideal, noise, steps=10), star.expand(3, 6, 2), atol=1e-3, rtol=0)  # float32: alpha_bar_99 = 2.4e-7
    with pytest.raises(ValueError, match="DDIM steps must be in 1..100"):
        objective.sample(ideal, noise, steps=101)


def test_objectives_are_chosen_by_name_with_clear_errors():
    assert set(OBJECTIVES) == {"icfm", "otcfm", "ddpm"}
    assert build_objective("ddpm", train_steps=50).train_steps == 50
    with pytest.raises(ValueError, match="unknown objective 'flow'"):
        build_objective("flow")
    with pytest.raises(ValueError, match="bad options"):
        build_objective("icfm", sigma=0.1)
    with pytest.raises(ValueError, match="train_steps must be an integer >= 2"):
        DDPM(train_steps=1)
