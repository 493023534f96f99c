"""The generative objectives in closed form: I-CFM and OT-CFM interpolants and targets, DDPM forward noising against
the squared-cosine schedule, one DDIM step on a one-point dataset, MeanFlow's target and one step on a one-point
dataset, reflow's straight couplings of a known teacher; the ODE solvers' order on a linear ODE."""

import math

import numpy as np
import pytest
import torch

from kpflow.policies.kcfm.objectives import DDPM, ICFM, OBJECTIVES, OTCFM, SOLVERS, MeanFlow, Reflow, build_objective
from kpflow.policies.kcfm.objectives.otcfm import exact_plan
from kpflow.policies.kcfm.objectives.solvers import integrate, intervals


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
    out = integrate(lambda x, t: (star - x) / (1 - t[:, None, None]), torch.randn(1, 4, 2), 1)
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
    a = exact_plan(torch.cat([x0.flatten(1), 10**0.5 * cond], 1), torch.cat([x1.flatten(1), 10**0.5 * cond], 1))
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
    torch.testing.assert_close(
        objective.sample(ideal, noise, steps=1), star.expand(3, 6, 2), atol=1e-3, rtol=0
    )  # float32: alpha_bar_99 = 2.4e-7
    torch.testing.assert_close(
        objective.sample(ideal, noise, steps=10), star.expand(3, 6, 2), atol=1e-3, rtol=0
    )  # float32: alpha_bar_99 = 2.4e-7
    with pytest.raises(ValueError, match="DDIM steps must be in 1..100"):
        objective.sample(ideal, noise, steps=101)


def test_objectives_are_chosen_by_name_with_clear_errors():
    assert set(OBJECTIVES) == {"icfm", "otcfm", "ddpm", "meanflow", "reflow"}
    assert build_objective("ddpm", train_steps=50).train_steps == 50
    with pytest.raises(ValueError, match="unknown objective 'flow'"):
        build_objective("flow")
    with pytest.raises(ValueError, match="bad options"):
        build_objective("icfm", sigma=0.1)
    with pytest.raises(ValueError, match="train_steps must be an integer >= 2"):
        DDPM(train_steps=1)


# ------------------------------------------------------------------------------------------------ solvers


def _count(field):
    """``field`` that counts its calls in ``.calls``."""

    def counted(x, t):
        counted.calls += 1
        return field(x, t)

    counted.calls = 0
    return counted


def test_solvers_spend_exactly_their_budget_of_network_calls():
    for solver in SOLVERS:
        for calls in (1, 2, 3, 4, 10, 20):
            field = _count(lambda x, t: -x)
            integrate(field, torch.ones(2, 3, 1), calls, solver)
            assert field.calls == calls, (solver, calls)
    assert intervals(5, "midpoint") == ["midpoint", "midpoint", "euler"] and intervals(1, "heun") == ["euler"]
    with pytest.raises(ValueError, match="unknown ODE solver 'rk4'"):
        intervals(4, "rk4")
    with pytest.raises(ValueError, match="network calls must be an integer >= 1"):
        intervals(0, "euler")


@pytest.mark.parametrize(("solver", "order"), [("euler", 1), ("midpoint", 2), ("heun", 2)])
def test_solver_order_on_a_linear_ode(solver, order):
    # dx/dt = a x + b t (non-autonomous, so the time each call is made at matters): the exact x(1) is known in
    # closed form; halving the step divides the global error by 2^order
    a, b, x0 = -1.5, 2.0, torch.tensor([[[1.0]]], dtype=torch.float64)
    exact = (x0 + b / a**2) * math.exp(a) - b / a**2 - b / a
    errors = [
        (integrate(lambda x, t: a * x + b * t[:, None, None], x0, calls, solver) - exact).abs().item()
        for calls in (32, 64, 128, 256)
    ]
    ratios = [e0 / e1 for e0, e1 in zip(errors, errors[1:])]
    assert all(abs(math.log2(r) - order) < 0.15 for r in ratios), (errors, ratios)


# ----------------------------------------------------------------------------------------------- MeanFlow


def _point_field(star):
    """The exact average velocity of a one-point dataset ``{x*}``: ``u(x_s, s, t) = (x* - x_s) / (1 - s)`` for every
    ``t`` (every trajectory is the straight line to ``x*``), as a network ``u(x, (s, t), c)``."""
    return lambda x, st, c=None: (star - x) / (1 - st[:, 0, None, None])


def test_meanflow_target_is_the_exact_average_velocity_on_a_one_point_dataset():
    # with the exact u, the MeanFlow identity u = v + (t - s)(v . d_x u + d_s u) holds at every drawn (x_s, s, t):
    # the target the objective builds by a Jacobian-vector product equals the network's own output
    star = torch.tensor([[[0.3, -0.7]] * 5], dtype=torch.float64)
    x1 = star.expand(64, 5, 2).clone()
    target = MeanFlow(flow_fraction=0.25).training_target(
        x1, None, torch.Generator().manual_seed(0), _point_field(star)
    )
    s, t = target.t[:, 0], target.t[:, 1]
    assert target.t.shape == (64, 2) and (s <= t).all() and (s < t).any() and (s == t).any()
    torch.testing.assert_close(target.target, _point_field(star)(target.x_t, target.t))
    # the sign of the time tangent matters: the target of a field that is right for s = t only is not its output
    wrong = lambda x, st, c=None: (star - x) / (1 - st[:, 1, None, None])  # noqa: E731  (uses t instead of s)
    off = MeanFlow(flow_fraction=0.0).training_target(x1, None, torch.Generator().manual_seed(0), wrong)
    assert not torch.allclose(off.target, wrong(off.x_t, off.t))


def test_meanflow_one_step_recovers_a_one_point_dataset_and_its_times():
    star = torch.tensor([[[0.5, 2.0]] * 4])
    noise = torch.randn(3, 4, 2, generator=torch.Generator().manual_seed(1))
    for steps in (1, 2, 5):
        torch.testing.assert_close(MeanFlow().sample(_point_field(star), noise, steps), star.expand(3, 4, 2))
    st = MeanFlow(flow_fraction=0.75).times(20000, torch.zeros(1), torch.Generator().manual_seed(0))
    equal = (st[:, 0] == st[:, 1]).float().mean().item()
    assert abs(equal - 0.75) < 0.02 and (st[:, 0] <= st[:, 1]).all() and st.min() >= 0 and st.max() <= 1
    with pytest.raises(ValueError, match="depends on the network"):
        MeanFlow().training_target(star)
    with pytest.raises(ValueError, match="flow_fraction must be in"):
        MeanFlow(flow_fraction=1.5)


# ------------------------------------------------------------------------------------------------- reflow


def test_reflow_regresses_the_straight_line_to_its_teachers_sample():
    # teacher: the exact transport of N(0, I) onto N(mu, sigma^2 I), x1_hat = mu + sigma x0 (a 1-D monotone map per
    # coordinate): every target is x1_hat - x0 at a point of the line between them, and one Euler step of that
    # target from x0 lands on the teacher's sample
    mu, sigma = torch.tensor([0.5, -1.0]), 0.3
    objective = Reflow(teacher="unused.ckpt", t_grid=None)
    objective.attach(lambda x0, c: mu + sigma * x0)
    x1 = torch.zeros(32, 6, 2)  # the data chunks themselves are not used, only their shape
    target = objective.training_target(x1, None, torch.Generator().manual_seed(0))
    g = torch.Generator().manual_seed(0)
    x0 = torch.randn(x1.shape, generator=g)
    x1_hat = mu + sigma * x0
    torch.testing.assert_close(target.target, x1_hat - x0)
    t = target.t[:, None, None]
    torch.testing.assert_close(target.x_t, t * x1_hat + (1 - t) * x0)
    torch.testing.assert_close(x0 + target.target, x1_hat)
    # on the grid of a 2-step sampler, t is 0 or 1/2 only
    grid = Reflow(teacher="unused.ckpt", t_grid=2)
    grid.attach(lambda x0, c: mu + sigma * x0)
    assert set(grid.training_target(torch.zeros(200, 2, 2), None, torch.Generator().manual_seed(0)).t.tolist()) == {
        0.0,
        0.5,
    }


def test_reflow_needs_its_teacher_and_checks_its_options():
    with pytest.raises(ValueError, match="attach the teacher first"):
        Reflow(teacher="t.ckpt").training_target(torch.zeros(2, 3, 2))
    with pytest.raises(ValueError, match="teacher must be the path"):
        Reflow(teacher="")
    with pytest.raises(ValueError, match="t_grid must be None or an integer >= 1"):
        Reflow(teacher="t.ckpt", t_grid=0)


def test_the_straight_path_and_the_exact_plan_in_closed_form():
    """x_t = t x1 + (1 - t) x0, u_t = x1 - x0 (paths.straight_path); the exact plan of a permuted set is that
    permutation with mass 1/B each (otcfm.exact_plan, POT's emd), shapes checked."""
    from kpflow.policies.kcfm.objectives.paths import straight_path

    x0, x1, t = torch.zeros(3, 2, 2), torch.ones(3, 2, 2), torch.tensor([0.0, 0.25, 1.0])
    x_t, u_t = straight_path(x0, x1, t)
    assert torch.equal(x_t[:, 0, 0], t) and torch.equal(u_t, x1)
    with pytest.raises(ValueError, match="one shape and t"):
        straight_path(x0, x1[:2], t)
    a = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    np.testing.assert_array_equal(exact_plan(a, a[[2, 0, 1]]), np.eye(3)[[1, 2, 0]] / 3)
