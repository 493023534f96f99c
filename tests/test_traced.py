"""The traced network: the eager network's outputs for every input signature, one trace per signature, the eager
network wherever a trace cannot be recorded, and new weights seen by existing traces."""

import torch

from kpflow.policies.kcfm.networks.unet1d import ConditionalUnet1D
from kpflow.policies.kcfm.traced import TracedNetwork


def test_traces_equal_the_eager_network_per_signature_and_follow_its_weights():
    net = ConditionalUnet1D(2, 10, (16, 32), time_dim=16).eval()
    traced = TracedNetwork(net)
    g = torch.Generator().manual_seed(0)
    for b, h in ((1, 16), (4, 16), (1, 9), (1, 16)):
        x, t, c = torch.randn(b, h, 2, generator=g), torch.rand(b, generator=g), torch.randn(b, 10, generator=g)
        with torch.no_grad():
            assert torch.equal(traced(x, t, c), net(x, t, c))
    assert len(traced.traces) == 3 and all(trace is not None for trace in traced.traces.values())
    with torch.no_grad():  # the traces share the network's parameters: loading weights reaches them
        for p in net.parameters():
            p.mul_(1.5)
        assert torch.equal(traced(x, t, c), net(x, t, c))


def test_a_network_that_cannot_be_traced_runs_eagerly():
    class Untraceable(torch.nn.Module):
        def forward(self, x, t, c):
            if torch.jit.is_tracing():
                raise RuntimeError("not traceable")
            return x * 2 + t[:, None, None]

    traced = TracedNetwork(Untraceable())
    x, t, c = torch.ones(2, 3, 1), torch.tensor([0.5, 1.0]), torch.zeros(2, 4)
    assert torch.equal(traced(x, t, c), x * 2 + t[:, None, None])
    assert list(traced.traces.values()) == [None]


def test_a_network_that_declares_itself_untraceable_is_never_traced():
    class Dynamic(torch.nn.Module):
        traceable = False

        def forward(self, x, t, c):
            assert not torch.jit.is_tracing()
            return x + 1

    traced = TracedNetwork(Dynamic())
    x = torch.zeros(1, 3, 2)
    assert torch.equal(traced(x, torch.zeros(1), torch.zeros(1, 4)), x + 1) and traced.traces == {}
