"""The learned map (issue 16): conditional flow, LearnedMap, its training module and keypoint-pair data."""

import numpy as np
import pytest
import torch

from kpflow.data.keypoint_pairs import KeypointPairDataModule, add_queries
from kpflow.maps import AffineMap, ILWRMap, LearnedMap
from kpflow.maps.base import jacobian_autograd
from kpflow.maps.conditional_flow import ConditionalFlow
from kpflow.maps.learned import load_flow, normalise
from kpflow.maps.map_module import KeypointPairs, MapModule
from kpflow.utils.checkpoint import load_checkpoint
from tests.helpers import grid, keypoint_pair, rotation, train_learned_map


def random_flow(n: int = 25, d: int = 2, layers: int = 4, seed: int = 0, depth: int = 2) -> ConditionalFlow:
    """A flow with every weight random (the zero-initialised last layers too), so it is far from the identity."""
    flow = ConditionalFlow(n, d, n_layers=layers, hidden=16, context=16, seed=seed, coupling_depth=depth).double()
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in flow.parameters():
            p.copy_(0.3 * torch.randn(p.shape, generator=g, dtype=p.dtype))
    return flow.requires_grad_(False)


def random_condition(flow: ConditionalFlow, b: int = 3, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(b, flow.n_keypoints, flow.dim, generator=g, dtype=torch.float64)
    return flow.condition(a, a + 0.3 * torch.randn(a.shape, generator=g, dtype=torch.float64))


@pytest.mark.parametrize(("d", "depth"), [(2, 2), (3, 2), (2, 1)])
def test_flow_inverts_exactly_on_random_conditions(d, depth):
    flow = random_flow(d=d, depth=depth)
    cond = random_condition(flow)
    u = 3 * torch.randn(3, 200, d, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    y = flow(u, cond)
    assert (y - u).abs().max() > 0.05  # not the identity
    torch.testing.assert_close(flow.inverse(y, cond), u, atol=1e-10, rtol=0)


@pytest.mark.parametrize("d", [2, 3])
def test_flow_log_det_is_that_of_its_jacobian_and_positive(d):
    flow = random_flow(d=d)
    cond = random_condition(flow)
    u = grid(d, lo=-3, hi=3, n=7 if d == 2 else 4).expand(3, -1, -1).contiguous()
    jac = jacobian_autograd(lambda x: flow(x, cond), u)
    sign, logdet = torch.linalg.slogdet(jac)
    assert (sign > 0).all()
    torch.testing.assert_close(flow.log_det(u, cond), logdet, atol=1e-9, rtol=0)


def test_flow_is_the_identity_when_the_pair_is_aligned():
    flow = random_flow()
    a = torch.randn(2, 25, 2, dtype=torch.float64)
    u = 2 * torch.randn(2, 50, 2, dtype=torch.float64)
    torch.testing.assert_close(flow(u, flow.condition(a, a)), u, atol=1e-12, rtol=0)  # the rotations' rounding


@pytest.mark.parametrize("d", [2, 3])  # 3-D: a robosuite segment's keypoints all belong to one rigid object
def test_learned_map_is_the_identity_for_s_equal_t_and_the_rigid_motion_for_a_rigid_pair(d):
    src, _ = keypoint_pair(d)
    x = grid(d, n=8 if d == 2 else 5)
    phi = LearnedMap(flow=random_flow(d=d)).fit(src, src)
    torch.testing.assert_close(phi(x), x, atol=1e-12, rtol=0)
    shift = torch.tensor([0.4, -0.2, 0.1][:d], dtype=src.dtype)
    tgt = src @ rotation(d, 0.7).T + shift
    phi = LearnedMap(flow=random_flow(d=d)).fit(src, tgt)
    torch.testing.assert_close(phi(x), x @ rotation(d, 0.7).T + shift, atol=1e-12, rtol=0)


@pytest.mark.parametrize("refine_steps", [0, 3])
def test_learned_map_inverse_jacobian_and_log_det(refine_steps):
    src, tgt = keypoint_pair(2)
    phi = LearnedMap(flow=random_flow(), refine_steps=refine_steps).fit(src, tgt)
    x = grid(2, n=10)  # three times the keypoints' extent
    y = phi(x)
    torch.testing.assert_close(phi.inverse(y), x, atol=1e-8, rtol=0)
    jac = phi.jacobian(x)
    h = 1e-6
    fd = torch.stack([(phi(x + h * e) - phi(x - h * e)) / (2 * h) for e in torch.eye(2, dtype=x.dtype)], -1)
    torch.testing.assert_close(jac, fd, atol=1e-6, rtol=1e-6)
    sign, logdet = torch.linalg.slogdet(jac)
    assert (sign > 0).all()
    torch.testing.assert_close(phi.log_det_jacobian(x), logdet, atol=1e-8, rtol=0)


def test_refinement_reduces_the_keypoint_residual():
    src, tgt = keypoint_pair(2)
    plain = LearnedMap(flow=random_flow()).fit(src, tgt)
    refined = LearnedMap(flow=random_flow(), refine_steps=30).fit(src, tgt)
    err = lambda m: (m(src) - tgt).norm(dim=-1).max()  # noqa: E731
    assert err(refined) < 0.1 * err(plain)


def test_batched_equals_looped():
    pairs = [keypoint_pair(2, seed=s) for s in range(4)]
    src, tgt = torch.stack([p[0] for p in pairs]), torch.stack([p[1] for p in pairs])
    x = grid(2, n=5)
    flow = random_flow()
    batched = LearnedMap(flow=flow).fit(src, tgt)
    out = batched(x.expand(4, -1, -1))
    for i in range(4):
        one = LearnedMap(flow=flow).fit(src[i], tgt[i])
        torch.testing.assert_close(out[i], one(x), atol=1e-12, rtol=0)
        torch.testing.assert_close(batched.inverse(out)[i], one.inverse(out[i]), atol=1e-12, rtol=0)


def test_bad_inputs_get_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="trained on 25 keypoints in 2-D; got 10 keypoints"):
        LearnedMap(flow=random_flow()).fit(*keypoint_pair(2, n=10))
    with pytest.raises(FileNotFoundError, match="no learned-map checkpoint"):
        LearnedMap(checkpoint=tmp_path / "missing.ckpt")
    with pytest.raises(ValueError, match="exactly one of checkpoint"):
        LearnedMap()
    with pytest.raises(ValueError, match="refine_steps"):
        LearnedMap(flow=random_flow(), refine_steps=-1)
    with pytest.raises(ValueError, match="alignment"):
        MapModule(n_keypoints=25, alignment="shear")


def test_add_queries_targets_are_where_ilwr_carries_them():
    src, tgt = (torch.stack([p] * 2).numpy() for p in keypoint_pair(2))
    pairs = add_queries(src, tgt, 8, np.random.default_rng(0))
    assert pairs.queries.shape == (2, 8, 2) and pairs.source.dtype == torch.float32
    expected = ILWRMap().fit(torch.from_numpy(src), torch.from_numpy(tgt))(pairs.queries.double())
    torch.testing.assert_close(pairs.query_targets, expected.float(), atol=1e-4, rtol=0)


def _one_pair(n, rng):
    src, tgt = keypoint_pair(2, n=12)
    return np.repeat(src.numpy()[None], n, 0), np.repeat(tgt.numpy()[None], n, 0)


def test_datamodule_is_seeded_and_checks_its_sampler():
    a, b = (
        KeypointPairDataModule(
            lambda n, rng: (rng.random((n, 5, 2)), rng.random((n, 5, 2))), n_pairs=20, n_queries=4, seed=3
        )
        for _ in range(2)
    )
    for dm in (a, b):
        dm.setup()
    torch.testing.assert_close(a.train_set.queries, b.train_set.queries)
    batch = next(iter(a.train_dataloader()))
    assert isinstance(batch, KeypointPairs) and len(batch) == 18 and len(a.val_set) == 2
    bad = KeypointPairDataModule(lambda n, rng: (np.zeros((n, 5, 2)), np.zeros((n, 4, 2))), n_pairs=4)
    with pytest.raises(ValueError, match="pair sampler must return"):
        bad.setup()


def test_a_map_trained_on_one_pair_interpolates_it(tmp_path):
    ckpt = train_learned_map(tmp_path, _one_pair, n_keypoints=12, steps=150)
    src, tgt = keypoint_pair(2, n=12)
    phi = LearnedMap(checkpoint=ckpt).fit(src, tgt)
    before = (AffineMap().fit(src, tgt)(src) - tgt).norm(dim=-1).max()  # the rigid alignment's residual
    err = (phi(src) - tgt).norm(dim=-1).max()
    assert err < 0.2 * before, (err, before)


def test_checkpoint_round_trip(tmp_path):
    ckpt = train_learned_map(tmp_path, _one_pair, n_keypoints=12, steps=3)
    module = load_checkpoint(MapModule, ckpt)
    flow, alignment = load_flow(ckpt)
    assert alignment == "rigid" and flow.n_keypoints == 12
    src, tgt = keypoint_pair(2, n=12)
    phi = LearnedMap(checkpoint=ckpt).fit(src, tgt)
    a, b, m, sigma = normalise(phi.alignment(src), tgt[None])
    ref = module.flow.double()
    expected = ref(a, ref.condition(a, b)) * sigma + m
    torch.testing.assert_close(phi(src), expected[0], atol=1e-10, rtol=0)
    for n in (25, 5):  # more or fewer than trained
        with pytest.raises(ValueError, match=f"trained on 12 keypoints in 2-D; got {n} keypoints"):
            LearnedMap(checkpoint=ckpt).fit(*keypoint_pair(2, n=n))


@pytest.mark.parametrize(("d", "depth"), [(2, 2), (3, 2), (2, 1)])
def test_compiled_path_equals_the_torch_layers(d, depth):
    src, tgt = keypoint_pair(d)
    src, tgt = torch.stack([src, src + 0.1]), torch.stack([tgt, tgt * 1.1])
    flow = random_flow(d=d, depth=depth)
    fast, slow = LearnedMap(flow=flow).fit(src, tgt), LearnedMap(flow=flow, compiled=False).fit(src, tgt)
    assert fast._packed is not None and slow._packed is None
    x = grid(d, n=6 if d == 2 else 4)
    y = slow(x)
    torch.testing.assert_close(fast(x), y, atol=1e-10, rtol=0)
    torch.testing.assert_close(fast.inverse(y), slow.inverse(y), atol=1e-10, rtol=0)
    torch.testing.assert_close(fast.jacobian(x), slow.jacobian(x), atol=1e-10, rtol=0)  # gradients: the torch layers


def test_pairs_that_require_grad_fit_under_no_grad():
    src, tgt = keypoint_pair(2)
    with torch.no_grad():
        phi = LearnedMap(flow=random_flow()).fit(src.requires_grad_(True), tgt)
        assert phi._packed is not None and torch.isfinite(phi(src)).all()


def test_distillation_needs_query_points():
    src, tgt = (torch.stack([p] * 2).float() for p in keypoint_pair(2))
    module = MapModule(n_keypoints=25, n_layers=2, hidden=8, context=8, distill_weight=1.0)
    no_queries = KeypointPairs(src, tgt, src[:, :0], tgt[:, :0])
    with pytest.raises(ValueError, match="distill_weight > 0 needs query points"):
        module.losses(no_queries)
    assert "distill" not in MapModule(n_keypoints=25, n_layers=2, hidden=8, context=8).losses(no_queries)
    with_queries = add_queries(src.double().numpy(), tgt.double().numpy(), 4, np.random.default_rng(0))
    out = module.losses(with_queries)
    assert torch.isfinite(out["distill"]) and out["loss"] >= out["keypoints"] + out["distill"]
