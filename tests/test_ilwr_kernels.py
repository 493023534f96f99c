"""ILWR's compiled kernels (kpflow/maps/ilwr_kernels.py) give the torch path's numbers: the same steps, the same
transported points, to 1e-9 in float64, on random, clustered, batched-then-split and early-stopping fits."""

import pytest
import torch

from kpflow.maps import ILWRMap, ilwr_kernels
from tests.helpers import grid, keypoint_pair


def pair(seed: int, n: int = 25, d: int = 2, scale: float = 512.0):
    g = torch.Generator().manual_seed(seed)
    src = torch.rand(n, d, generator=g, dtype=torch.float64) * scale
    if seed % 2:  # two tight clusters: the case where neighbouring steps interact most
        src[: n // 2] = src[: n // 2] * 0.05 + 0.2 * scale
    tgt = src + 0.03 * scale * torch.sin(src / (0.12 * scale) + seed) + 0.04 * scale
    return src, tgt


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("d", [2, 3])
def test_fused_fit_and_forward_equal_the_torch_path(seed, d):
    src, tgt = pair(seed, d=d)
    fused, plain = ILWRMap().fit(src, tgt), ILWRMap(fused=False).fit(src, tgt)
    for name in ("centres", "vectors", "neg_rho2"):
        torch.testing.assert_close(getattr(fused, name), getattr(plain, name), atol=1e-9, rtol=1e-9)
    x = grid(d, lo=-100.0, hi=600.0, n=7)
    torch.testing.assert_close(fused(x), plain(x), atol=1e-9, rtol=0)
    torch.testing.assert_close(fused.inverse(fused(x)), x, atol=1e-7, rtol=0)  # the inverse still undoes it


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("d", [2, 3])
def test_the_fused_inverse_and_jacobian_equal_the_torch_path(seed, d):
    src, tgt = pair(seed, d=d)
    fused, plain = ILWRMap().fit(src, tgt), ILWRMap(fused=False).fit(src, tgt)
    y = grid(d, lo=-100.0, hi=600.0, n=7)
    torch.testing.assert_close(fused.inverse(y), plain.inverse(y), atol=1e-9, rtol=0)
    torch.testing.assert_close(fused(fused.inverse(y)), y, atol=1e-9, rtol=0)
    torch.testing.assert_close(fused.jacobian(y), plain.jacobian(y), atol=1e-9, rtol=1e-9)


def test_early_stopping_and_other_settings_agree():
    src, tgt = keypoint_pair(2)
    settings = ({"tol": 1e-3}, {"n_steps": 5, "beta": 0.5}, {"n_rho": 4, "alignment": "none"},
                {"alignment": "similarity"}, {"alignment": "translation"}, {"alignment": "affine"})  # fmt: skip
    for kwargs in settings:
        fused, plain = ILWRMap(**kwargs).fit(src, tgt), ILWRMap(fused=False, **kwargs).fit(src, tgt)
        assert fused.centres.shape == plain.centres.shape
        torch.testing.assert_close(fused.alignment.A, plain.alignment.A, atol=1e-12, rtol=0)
        torch.testing.assert_close(fused.alignment.t, plain.alignment.t, atol=1e-9, rtol=0)
        torch.testing.assert_close(fused(src), plain(src), atol=1e-9, rtol=0)


def test_the_compiled_alignment_is_reflection_safe_and_names_coincident_sources():
    src, _ = pair(3)
    mirrored = src * torch.tensor([-1.0, 1.0], dtype=torch.float64)  # a reflection: the rigid fit must not mirror
    phi = ILWRMap(n_steps=1).fit(src, mirrored)
    assert torch.linalg.det(phi.alignment.A[0]) > 0
    torch.testing.assert_close(
        phi.alignment.A, ILWRMap(n_steps=1, fused=False).fit(src, mirrored).alignment.A, atol=1e-12, rtol=0
    )
    same = torch.full((5, 2), 3.0, dtype=torch.float64)
    with pytest.raises(ValueError, match="all source keypoints coincide"):
        ILWRMap().fit(same, same + 1.0)  # one point five times: the rotation is undetermined


@pytest.mark.parametrize("kwargs", [{"n_steps": 5}, {"n_steps": 1, "alignment": "none"}])
def test_a_target_that_wants_gradients_takes_the_differentiable_path(kwargs):
    src, tgt = pair(1)
    tgt = tgt.clone().requires_grad_(True)
    phi = ILWRMap(**kwargs).fit(src, tgt)  # (one unaligned step: the centres do not depend on the targets)
    (grad,) = torch.autograd.grad(phi(src).sum(), tgt)
    assert grad.abs().sum() > 0  # the fit is differentiable in its targets


def test_an_ill_determined_rotation_is_decided_as_the_torch_path_decides_it():
    t = torch.linspace(0.0, 1.0, 6, dtype=torch.float64)[:, None]
    src = t * torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)  # collinear in 3-D: the spin about the line is free
    tgt = src + torch.tensor([0.1, 0.0, -0.2], dtype=torch.float64) + 0.01 * t**2
    finfo = torch.finfo(torch.float64)
    assert not ilwr_kernels.align(src.numpy(), tgt.numpy(), ilwr_kernels.ALIGN_KINDS["rigid"], finfo.eps, finfo.tiny)[2]
    fused, plain = ILWRMap().fit(src, tgt), ILWRMap(fused=False).fit(src, tgt)
    torch.testing.assert_close(fused.alignment.A, plain.alignment.A, atol=1e-12, rtol=0)
    torch.testing.assert_close(fused(src), plain(src), atol=1e-9, rtol=0)


def test_the_torch_path_keeps_what_the_kernels_do_not_cover():
    src, tgt = pair(0)
    batch = ILWRMap().fit(torch.stack([src, src + 1.0]), torch.stack([tgt, tgt + 1.0]))  # a batch: torch
    one = ILWRMap().fit(src, tgt)
    torch.testing.assert_close(batch(src[None].expand(2, -1, -1))[0], one(src), atol=1e-9, rtol=0)
    x = src.clone().requires_grad_(True)  # a query that wants gradients: torch, differentiable
    (grad,) = torch.autograd.grad(one(x).sum(), x)
    torch.testing.assert_close(grad, one.jacobian(src).sum(-2), atol=1e-8, rtol=1e-8)
    f32 = ILWRMap().fit(src.float(), tgt.float())  # float32: torch, so a float32 batch equals its sets fitted singly
    assert torch.equal(f32(src.float()), ILWRMap(fused=False).fit(src.float(), tgt.float())(src.float()))


@pytest.mark.parametrize("kind", sorted(ilwr_kernels.ALIGN_KINDS))
@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("seed", range(4))
def test_the_compiled_alignment_is_fit_affine(kind, d, seed):
    """``align`` is the compiled form of :func:`~kpflow.geometry.alignment.fit_affine` for one pair: the same A and t."""
    from kpflow.geometry.alignment import fit_affine

    src, tgt = pair(seed, n=9, d=d)
    finfo = torch.finfo(torch.float64)
    a, t, ok = ilwr_kernels.align(src.numpy(), tgt.numpy(), ilwr_kernels.ALIGN_KINDS[kind], finfo.eps, finfo.tiny)
    want_a, want_t = fit_affine(src[None], tgt[None], kind)
    assert ok
    torch.testing.assert_close(torch.from_numpy(a), want_a[0], atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.from_numpy(t), want_t[0], atol=1e-9, rtol=0)
