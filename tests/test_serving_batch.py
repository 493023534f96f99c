"""Batching the policy server's network calls (kpflow/serving/batching.py): rows from several threads run as one
forward pass and every caller gets its own rows back, equal to its lone call up to floating-point effects of the batch
size; a served reply equals the in-process, unbatched ``act`` on the same request sequence. Tiny networks only."""

import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from kpflow.cli.serve import KEYS
from kpflow.policies.kcfm.model import KCFM
from kpflow.policies.kcfm.networks.unet1d import ConditionalUnet1D
from kpflow.serving import PolicyClient, PolicyServer, load_deployment
from kpflow.serving.batching import BatchedNetwork, BatchedPolicy
from kpflow.tasks.pusht.task import PushTTask
from kpflow.utils.config_checks import check_config

CONF_SERVE = Path(__file__).resolve().parents[1] / "kpflow" / "conf" / "serve.yaml"
H, A, C = 8, 2, 6


class Counting(torch.nn.Module):
    """``net`` that counts its forward passes and the rows of each."""

    def __init__(self, net) -> None:
        super().__init__()
        self.net, self.batches = net, []

    def forward(self, x, t, c=None):
        self.batches.append(len(x))
        return self.net(x, t, c)


class Failing(torch.nn.Module):
    def forward(self, x, t, c=None):
        raise RuntimeError(f"the network broke on {len(x)} rows")


class RowWise(torch.nn.Module):
    """A row-wise toy network for any time shape: ``x * (1 + sum of t's row) + sum of c's row``, exact in float64."""

    def forward(self, x, t, c=None):
        t = torch.as_tensor(t, dtype=x.dtype).expand(len(x), *torch.as_tensor(t).shape[1:])
        y = x * (1 + t.reshape(len(x), -1).sum(-1))[:, None, None]
        return y if c is None else y + c.sum(-1)[:, None, None]


def unet() -> torch.nn.Module:
    torch.manual_seed(0)
    return ConditionalUnet1D(A, C, (16, 32), time_dim=16).eval().requires_grad_(False)


def calls(n: int, seed: int) -> list[tuple]:
    g = torch.Generator().manual_seed(seed)
    return [
        (torch.randn(1, H, A, generator=g), torch.rand(1, generator=g), torch.randn(1, C, generator=g))
        for _ in range(n)
    ]


def in_threads(target, n: int, batched: BatchedNetwork) -> tuple[dict, dict]:
    """Run ``target(i)`` in ``n`` threads released at once, each a request in flight on ``batched`` (as the server's
    policies are); their results and exceptions by ``i``."""
    results, errors, start = {}, {}, threading.Barrier(n)

    def run(i: int) -> None:
        try:
            with torch.no_grad(), batched.request():  # grad mode is per thread: a new thread records gradients
                start.wait()  # every request is in flight before the first call
                results[i] = target(i)
        except Exception as e:
            errors[i] = e

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    [t.start() for t in threads]
    [t.join(30) for t in threads]
    return results, errors


# ------------------------------------------------------------------------------------------------ BatchedNetwork


@pytest.mark.parametrize("trace", [False, True])
def test_rows_from_four_threads_are_their_lone_calls_in_fewer_passes(trace):
    net = unet()
    counted = Counting(net)
    batched = BatchedNetwork(counted, max_batch=4, max_wait_ms=500, trace=trace)
    sequences = {i: calls(3, seed=i) for i in range(4)}
    with torch.no_grad():
        lone = {i: [net(*args) for args in sequences[i]] for i in range(4)}
    results, errors = in_threads(lambda i: [batched(*args) for args in sequences[i]], 4, batched)
    assert not errors
    for i in range(4):
        for got, want in zip(results[i], lone[i]):
            assert got.shape == (1, H, A)
            torch.testing.assert_close(got, want, atol=1e-5, rtol=0)  # float32 kernels of another batch size
    stats = batched.stats()
    assert stats["calls"] == 12 and stats["rows"] == 12 and stats["passes"] < 12 and stats["mean_batch"] > 1  # merged
    if not trace:  # (a trace replays the network's operations without calling it)
        assert sum(counted.batches) == 12 and len(counted.batches) == stats["passes"]


def test_a_batched_network_is_not_traced_itself():
    """It declares itself untraceable, so a policy's TracedNetwork around the model's ema_net calls it eagerly
    (kpflow/policies/kcfm/traced.py, no trace recorded) and the batches are traced inside; tracing it anyway raises."""
    from kpflow.policies.kcfm.traced import TracedNetwork

    batched = BatchedNetwork(unet(), trace=True)
    outer = TracedNetwork(batched)
    x, t, c = calls(1, seed=5)[0]
    assert torch.equal(outer(x, t, c), batched(x, t, c)) and outer.traces == {}
    with pytest.raises(RuntimeError, match="not traced"):
        torch.jit.trace(batched, calls(1, seed=5)[0], check_trace=False)


@pytest.mark.parametrize("time_shape", ["scalar", "rows", "one", "pairs"])
def test_every_caller_gets_its_own_rows_whatever_the_time_shape(time_shape):
    """``t`` as a float, ``[B]``, ``[1]`` or ``[B, 2]`` (MeanFlow's two times); callers of 1 to 3 rows, with and
    without a condition. A row-wise network in float64 gives each caller exactly its lone result."""
    counted = Counting(RowWise())
    batched = BatchedNetwork(counted, max_batch=16, max_wait_ms=500)
    g = torch.Generator().manual_seed(0)

    def args(i: int) -> tuple:
        b = i % 3 + 1
        t = {"scalar": 0.1 * i, "rows": torch.rand(b, generator=g, dtype=torch.float64), "one": torch.full((1,), 0.2 * i, dtype=torch.float64),
             "pairs": torch.rand(b, 2, generator=g, dtype=torch.float64)}[time_shape]  # fmt: skip
        c = torch.randn(b, 3, generator=g, dtype=torch.float64) if i % 2 else None
        return torch.randn(b, H, A, generator=g, dtype=torch.float64), t, c

    requests = {i: args(i) for i in range(6)}
    results, errors = in_threads(lambda i: batched(*requests[i]), 6, batched)
    assert not errors
    for i, request in requests.items():
        torch.testing.assert_close(results[i], RowWise()(*request), atol=0, rtol=0)
    assert sum(counted.batches) == sum(len(r[0]) for r in requests.values()) and len(counted.batches) < 6


def test_a_forward_pass_exception_reaches_every_caller_of_its_batch():
    counted = Counting(Failing())
    batched = BatchedNetwork(counted, max_batch=4, max_wait_ms=500)
    args = calls(4, seed=1)
    results, errors = in_threads(lambda i: batched(*args[i]), 4, batched)
    assert not results and sorted(errors) == [0, 1, 2, 3]
    assert all(isinstance(e, RuntimeError) and "the network broke on" in str(e) for e in errors.values())
    assert len(counted.batches) < 4  # they shared passes, and every caller of each got its error
    with torch.no_grad(), batched.request(), pytest.raises(RuntimeError, match="broke on 1 rows"):  # it goes on
        batched(*calls(1, seed=2)[0])


def test_a_lone_request_does_not_wait_and_computes_the_same_bits():
    """Counted as the only request in flight (what the server's policies do), a call runs at once however long
    ``max_wait_ms`` is, on the caller's own tensors: the result is bit for bit the unbatched one."""
    net = unet()
    batched = BatchedNetwork(net, max_batch=8, max_wait_ms=2000)
    x, t, c = calls(1, seed=3)[0]
    start = time.monotonic()
    with torch.no_grad(), batched.request():
        for _ in range(5):
            got = batched(x, t, c)
    assert time.monotonic() - start < 1.0  # five calls, not five waits of 2 s
    with torch.no_grad():
        torch.testing.assert_close(got, net(x, t, c), atol=0, rtol=0)


def test_calls_that_record_gradients_go_straight_to_the_network():
    net = ConditionalUnet1D(A, C, (16, 32), time_dim=16)  # trainable
    counted = Counting(net)
    batched = BatchedNetwork(counted, max_wait_ms=2000)
    x, t, c = calls(1, seed=4)[0]
    start = time.monotonic()
    y = batched(x, t, c)
    assert (
        y.requires_grad and counted.batches == [1] and batched.stats()["calls"] == 0 and time.monotonic() - start < 1.0
    )


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"max_batch": 0}, "max_batch must be an integer >= 1"),
        ({"max_batch": -2}, "max_batch must be an integer >= 1"),
        ({"max_batch": 2.5}, "max_batch must be an integer >= 1"),
        ({"max_batch": True}, "max_batch must be an integer >= 1"),
        ({"max_wait_ms": -1}, "max_wait_ms must be a finite number of milliseconds >= 0"),
        ({"max_wait_ms": float("inf")}, "max_wait_ms must be a finite number"),
        ({"max_wait_ms": float("nan")}, "max_wait_ms must be a finite number"),
    ],
)
def test_bad_arguments_are_refused(kwargs, match, tmp_path):
    with pytest.raises(ValueError, match=match):
        BatchedNetwork(unet(), **kwargs)
    with pytest.raises(ValueError, match=match):  # before the checkpoint is even looked for
        load_deployment(tmp_path / "missing.ckpt", PushTTask(), **kwargs)


def test_a_wrapped_network_saves_and_loads_under_its_own_names():
    model = KCFM(25, horizon=H, network={"name": "unet", "down_dims": (16, 32), "time_dim": 16})
    before = model.state_dict()
    model.ema_net = BatchedNetwork(model.ema_net)
    after = model.state_dict()
    assert list(after) == list(before) and all(torch.equal(after[k], before[k]) for k in before)
    model.load_state_dict(before)  # as a checkpoint of the unwrapped model holds them
    assert "max_batch=8, max_wait_ms=5" in repr(model.ema_net)


# ------------------------------------------------------------------------------------------------ the server


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    """A tiny K-CFM for Push-T's 25 keypoints (untrained weights, statistics of random data, actions of order 1)."""
    torch.manual_seed(0)
    model = KCFM(25, horizon=H, network={"name": "unet", "down_dims": (16, 32), "time_dim": 16})
    rng = np.random.default_rng(0)
    model.processor.fit(rng.uniform(100, 400, (64, 25, 2)), rng.uniform(-1, 1, (64, H, 2)))
    path = tmp_path_factory.mktemp("batched") / "tiny.ckpt"
    torch.save({"state_dict": model.state_dict(), "hyper_parameters": dict(model.hparams)}, path)
    return path


def observation(seed: int) -> dict:
    return {"keypoints": np.random.default_rng(seed).uniform(100, 400, (25, 2))}


def test_four_clients_at_once_get_the_unbatched_replies(tiny_checkpoint):
    """4 clients send seeded request sequences at once to a batching server; each reply equals the in-process,
    unbatched policy's on the same sequence (the same noise, drawn from the connection's own generator), and the
    server ran fewer forward passes than it received network calls."""
    n_clients, n_requests, steps = 4, 8, 4
    plain = load_deployment(tiny_checkpoint, PushTTask(), {"steps": steps, "execute": 4})
    expected = {}
    for c in range(n_clients):
        local = plain.make_policy()
        local.reset(c)
        for r in range(n_requests):
            expected[c, r] = local.act(observation(10 * c + r))
    batched = load_deployment(tiny_checkpoint, PushTTask(), {"steps": steps, "execute": 4}, max_batch=8, max_wait_ms=20)
    assert isinstance(batched.make_policy(), BatchedPolicy) and batched.network is not None
    got, server_ms, failures, start = {}, [], [], threading.Barrier(n_clients)

    def drive(c: int) -> None:
        try:
            with PolicyClient(address) as client:
                client.reset(c)
                start.wait()
                for r in range(n_requests):
                    got[c, r] = client.act(observation(10 * c + r))
                    server_ms.append(client.server_ms)
        except Exception as e:  # reported below
            failures.append(e)

    with PolicyServer(batched, port=0).running() as address:
        threads = [threading.Thread(target=drive, args=(c,)) for c in range(n_clients)]
        [t.start() for t in threads]
        [t.join(60) for t in threads]
        assert not failures and len(got) == n_clients * n_requests
        stats = batched.network.stats()
        assert stats["calls"] == n_clients * n_requests * steps and stats["passes"] < stats["calls"]
        assert len(server_ms) == len(got) and min(server_ms) > 0  # each reply still times its own request
        for key, actions in expected.items():
            np.testing.assert_allclose(got[key], actions, atol=1e-5, rtol=0)
        # a lone client of the batching server computes exactly the unbatched bits
        local = plain.make_policy()
        with PolicyClient(address) as client:
            client.reset(9), local.reset(9)
            for r in range(3):
                np.testing.assert_array_equal(client.act(observation(r)), local.act(observation(r)))


def test_serve_config_turns_batching_on_and_checks_it():
    cfg = OmegaConf.load(CONF_SERVE)
    assert cfg.batch.max_size == 8 and cfg.batch.max_wait_ms == 5.0
    check_config(cfg, KEYS)
    for key, value, match in (
        ("max_size", 0, "batch.max_size must be an integer >= 1"),
        ("max_wait_ms", -1.0, "batch.max_wait_ms must be a finite number"),
    ):
        bad = OmegaConf.merge(cfg, {"batch": {key: value}})
        with pytest.raises(ValueError, match=match):
            check_config(bad, KEYS)
