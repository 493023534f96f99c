"""Dynamic batching of a shared network: calls from several threads run as one forward pass.

The policy server answers each connection's ``act`` in a worker thread, and every connection's policy shares one
loaded K-CFM (:mod:`kpflow.serving.deployment`). ``act`` ends in :meth:`~kpflow.policies.kcfm.KCFM.sample`, which
calls the model's ``ema_net(x [B, H, A], t, c [B, C])`` once per solver step with ``B = 1`` (through a
:class:`~kpflow.policies.kcfm.traced.TracedNetwork` of it). On a CPU such a call of a small network costs far less than
proportionally more for more rows (one pass of eight rows of the released Push-T U-Net takes a few times one row's,
``results/serving.md``). :class:`BatchedNetwork` is a drop-in for ``ema_net`` that gathers the
calls arriving from different threads within a bounded wait and runs them as one pass: the dynamic batching of
inference servers (NVIDIA Triton's dynamic batcher, with its ``max_batch_size`` and ``max_queue_delay_microseconds``;
Clipper, Crankshaw et al., NSDI 2017, Sec. 4.3), done at the level of the network call so that it serves every
objective, solver and policy (bare or transported K-CFM) without knowing them. What it can gain is bounded by that
cost curve: with passes of 4 rows costing about twice one of 1 row, four clients get at most about twice the
network-bound rate of one (``benchmarks/serving.py``, ``results/serving.md``).

How it works (leader/follower). A caller queues its ``(x, t, c)``. The first caller that finds nobody leading a
batch leads one: it waits until the queued calls hold ``max_batch`` rows, or cover every request in flight
(:meth:`BatchedNetwork.request`: then nobody else can come), or the oldest queued call has waited ``max_wait_ms``.
It then takes the oldest queued calls whose shapes fit together (``x``, ``t`` and ``c`` alike past the batch
dimension, ``t`` broadcast to one value per row first: ``[B]``, or ``[B, 2]`` for two times), up to ``max_batch`` rows,
concatenates them along the batch dimension, runs the wrapped network once under ``torch.no_grad()`` outside the lock,
and hands every caller its own rows, or the pass's exception (each caller of that batch raises it). The next queued
caller then leads the next batch; a caller that finds its rows already computed returns at once. While a pass runs,
new calls queue, so under load the batches fill without waiting. Requests are counted by the policies of a batching
deployment (:class:`BatchedPolicy`): a lone request never waits, and a batch of one call runs the caller's own tensors
as given, so batching on and off compute the same bits for a lone client. Calls nobody counts wait up to
``max_wait_ms`` for ``max_batch`` rows.

What a batched result is. The network must be row-wise: each output row a function of its own input row (true of
kpflow's U-Net and transformer in eval mode: GroupNorm and attention act within a row). Every request draws its
noise from its own policy's generator before the network runs, so a batched reply differs from the unbatched one
only by the floating-point effects of the batch size (a CPU convolution of several rows takes another kernel than
one of a single row: oneDNN instead of the direct one): about 1e-6 of the actions' scale (2e-4 px on Push-T's 512 px
board after 10 steps).

Calls that cannot be batched go straight to the network, unbatched: any call while autograd would record it
(gradients enabled and an input or a parameter requiring them: training), and a ``t`` that is not one value per row
(its first dimension neither 1 nor ``B``).
"""

from __future__ import annotations

import math
import numbers
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Iterator

import torch
from torch import nn

DEFAULT_MAX_BATCH = 8
DEFAULT_MAX_WAIT_MS = 5.0


@dataclass(eq=False)
class _Call:
    """One caller's rows: the network's arguments as given (``args``) and with ``t`` broadcast per row."""

    args: tuple
    x: torch.Tensor
    t: torch.Tensor
    c: torch.Tensor | None
    key: tuple
    rows: int
    arrived: float = 0.0  # time.monotonic() when queued
    out: torch.Tensor | None = None
    error: BaseException | None = None
    done: bool = False


def check_batching(max_batch: int, max_wait_ms: float) -> None:
    """``ValueError`` naming the value unless ``max_batch`` is an integer >= 1 and ``max_wait_ms`` a finite number >= 0."""
    if isinstance(max_batch, bool) or not isinstance(max_batch, numbers.Integral) or max_batch < 1:
        raise ValueError(
            f"max_batch must be an integer >= 1 (the most rows of one forward pass; 1: no batching); got {max_batch!r}"
        )
    if isinstance(max_wait_ms, bool) or not isinstance(max_wait_ms, numbers.Real) or not 0 <= max_wait_ms < math.inf:
        raise ValueError(f"max_wait_ms must be a finite number of milliseconds >= 0; got {max_wait_ms!r}")


def _per_row(x: Any, t: Any, c: Any) -> _Call | None:
    """The call with ``t`` as one value per row, or None if it cannot join a batch (module docstring)."""
    if not isinstance(x, torch.Tensor) or x.ndim < 1 or (c is not None and not isinstance(c, torch.Tensor)):
        return None
    b = x.shape[0]
    t_rows = t if isinstance(t, torch.Tensor) else torch.as_tensor(t, dtype=x.dtype, device=x.device)
    if t_rows.ndim == 0:
        t_rows = t_rows.expand(b)
    elif t_rows.shape[0] == 1 and b != 1:
        t_rows = t_rows.expand(b, *t_rows.shape[1:])
    elif t_rows.shape[0] != b:
        return None
    if c is not None and (c.ndim < 1 or c.shape[0] != b):
        return None
    c_key = None if c is None else (tuple(c.shape[1:]), c.dtype, c.device)
    key = (tuple(x.shape[1:]), x.dtype, x.device, tuple(t_rows.shape[1:]), t_rows.dtype, t_rows.device, c_key)
    return _Call((x, t, c), x, t_rows, c, key, b)


class BatchedNetwork(nn.Module):
    """``net(x, t, c)``, thread-safe, with concurrent calls run as one batch (module docstring).

    Args:
        net: the row-wise network (``ema_net`` of a K-CFM): ``net(x [B, ...], t, c [B, ...] | None) -> [B, ...]``.
        max_batch: the most rows one forward pass takes (a single call with more runs alone); 1 runs every call
            on its own.
        max_wait_ms: the longest a queued call waits for others before its batch runs (0: a batch takes what is
            queued); no wait at all once every request in flight (:meth:`request`) has a call queued.
        trace: run the passes through TorchScript traces of ``net``, one per batch size, each recorded at its first
            use (:class:`~kpflow.policies.kcfm.traced.TracedNetwork`: what a :class:`~kpflow.policies.kcfm.policy.KCFMPolicy`
            runs, so that a lone caller computes the bits an unbatched policy does); False: eagerly.

    A ``BatchedNetwork`` cannot itself be traced (it gathers the calls of several threads at run time): it declares
    ``traceable = False``, so a policy's :class:`~kpflow.policies.kcfm.traced.TracedNetwork` around the model's ``ema_net``
    calls it eagerly, and the tracing happens inside, per batch; tracing it anyway raises ``RuntimeError``.

    The wrapped network stays a submodule, and :meth:`state_dict` and :meth:`load_state_dict` read and write its keys
    without the wrapper's ``net.`` prefix, so a model holding a ``BatchedNetwork`` saves and loads as one holding
    ``net``. :meth:`stats` counts the network calls received, the forward passes run and their rows.
    """

    traceable = False  # kpflow.policies.kcfm.traced.TracedNetwork calls it eagerly

    def __init__(
        self,
        net: nn.Module,
        max_batch: int = DEFAULT_MAX_BATCH,
        max_wait_ms: float = DEFAULT_MAX_WAIT_MS,
        trace: bool = False,
    ) -> None:
        super().__init__()
        check_batching(max_batch, max_wait_ms)
        if not callable(net):
            raise ValueError(f"net must be a callable network, got {type(net).__name__}")
        self.net = net
        if trace:
            from ..policies.kcfm.traced import TracedNetwork

            self._traced = TracedNetwork(net)
        else:
            self._traced = None
        self.max_batch, self.max_wait_ms = int(max_batch), float(max_wait_ms)
        self._queue = _Queue(
            self.max_batch, self.max_wait_ms / 1e3
        )  # a plain object: no nn.Module attribute hooks per call
        self.register_state_dict_post_hook(_without_prefix)
        self.register_load_state_dict_pre_hook(_with_prefix)

    def extra_repr(self) -> str:
        return f"max_batch={self.max_batch}, max_wait_ms={self.max_wait_ms:g}"

    @contextmanager
    def request(self) -> Iterator[None]:
        """Count one request in flight for its duration (the server's ``act``): while requests are counted, a
        batch stops waiting as soon as every one of them has a call queued, and a lone request never waits."""
        queue = self._queue
        with queue.cond:
            queue.in_flight += 1
        try:
            yield
        finally:
            with queue.cond:
                queue.in_flight -= 1
                queue.cond.notify_all()  # a leader waiting for this request's call stops waiting

    def stats(self) -> dict[str, float]:
        """``calls`` (network calls received), ``passes`` (forward passes run), ``rows`` (rows run) so far, and
        ``mean_batch`` (rows per forward pass)."""
        queue = self._queue
        with queue.cond:
            return {
                "calls": queue.calls,
                "passes": queue.passes,
                "rows": queue.rows,
                "mean_batch": queue.rows / max(queue.passes, 1),
            }

    def forward(self, x: torch.Tensor, t: torch.Tensor | float, c: torch.Tensor | None = None) -> torch.Tensor:
        """``net(x, t, c)``, possibly computed in one pass with other threads' calls."""
        if torch.jit.is_tracing():
            raise RuntimeError(
                "a BatchedNetwork is not traced: it gathers the calls of several threads at run time (trace=True traces inside)"
            )
        net = self.net
        call = None if _needs_grad(net, x, t, c) else _per_row(x, t, c)
        if call is None:
            return net(x, t, c)
        return self._queue.submit(call, net if self._traced is None or c is None else self._traced)


def _needs_grad(net: nn.Module, *tensors) -> bool:
    """Whether autograd would record ``net`` on ``tensors``."""
    if not torch.is_grad_enabled():
        return False
    return any(isinstance(v, torch.Tensor) and v.requires_grad for v in tensors) or any(
        p.requires_grad for p in net.parameters()
    )


class _Queue:
    """The calls waiting for a forward pass, and the leader/follower protocol of the module docstring."""

    def __init__(self, max_batch: int, max_wait_s: float) -> None:
        self.max_batch, self.max_wait_s = max_batch, max_wait_s
        self.cond = threading.Condition()
        self.calls_waiting: list[_Call] = []
        self.leading = False  # a caller is gathering or running a batch
        self.in_flight = 0  # requests inside BatchedNetwork.request(): callers that may still come
        self.calls = self.passes = self.rows = 0

    def submit(self, call: _Call, net) -> torch.Tensor:
        """``call``'s rows of a forward pass of ``net``: led by this caller or by another."""
        with self.cond:
            self.calls += 1
            call.arrived = time.monotonic()
            self.calls_waiting.append(call)
            self.cond.notify_all()  # a leader gathering a batch counts this call
            while not call.done:
                if self.leading:
                    self.cond.wait()
                else:
                    self._lead(net)
        if call.error is not None:
            raise call.error
        return call.out

    def _gathered(self) -> bool:
        """Whether the queue is worth running now: ``max_batch`` rows, or every request in flight has a call queued."""
        waiting = self.calls_waiting
        return 0 < self.in_flight <= len(waiting) or sum(call.rows for call in waiting) >= self.max_batch

    def _lead(self, net) -> None:
        """Gather, run and hand out one batch (called holding the lock; released while the network runs)."""
        self.leading = True
        try:
            deadline = self.calls_waiting[0].arrived + self.max_wait_s  # the oldest call waits at most max_wait_ms
            while not self._gathered() and (left := deadline - time.monotonic()) > 0:
                self.cond.wait(left)
            batch = self._take()
            self.passes += 1
            self.rows += sum(call.rows for call in batch)
            self.cond.release()
            try:
                _run(net, batch)
            finally:
                self.cond.acquire()
        finally:
            self.leading = False
            self.cond.notify_all()  # the batch's callers return, and a queued caller leads the next batch

    def _take(self) -> list[_Call]:
        """The oldest queued calls that fit with the first, up to ``max_batch`` rows (the first one always)."""
        first, rows, batch, rest = self.calls_waiting[0], 0, [], []
        for call in self.calls_waiting:
            if call.key == first.key and (not batch or rows + call.rows <= self.max_batch):
                batch.append(call)
                rows += call.rows
            else:
                rest.append(call)
        self.calls_waiting = rest
        return batch


def _run(net, batch: list[_Call]) -> None:
    """Every call of ``batch`` gets its rows of one forward pass of ``net``, or that pass's exception."""
    try:
        with torch.no_grad():
            if len(batch) == 1:  # the caller's own tensors, as given: the unbatched result, bit for bit
                outs = [net(*batch[0].args)]
            else:
                c = None if batch[0].c is None else torch.cat([call.c for call in batch])
                y = net(torch.cat([call.x for call in batch]), torch.cat([call.t for call in batch]), c)
                rows = [call.rows for call in batch]
                if not isinstance(y, torch.Tensor) or y.ndim < 1 or y.shape[0] != sum(rows):
                    raise RuntimeError(
                        f"the batched network returned {_describe(y)} for {sum(rows)} rows; it must return one row per input row"
                    )
                outs = y.split(rows)
    except BaseException as e:  # every caller of the batch raises it
        for call in batch:
            call.error, call.done = e, True
        return
    for call, out in zip(batch, outs):
        call.out, call.done = out, True


def _describe(y: Any) -> str:
    return f"a tensor of shape {list(y.shape)}" if isinstance(y, torch.Tensor) else f"a {type(y).__name__}"


def _without_prefix(module: BatchedNetwork, state: dict, prefix: str, local_metadata: dict) -> None:
    """``state_dict`` hook: the wrapped network's keys as they were before it was wrapped."""
    for key in [k for k in state if k.startswith(prefix + "net.")]:
        state[prefix + key[len(prefix) + 4 :]] = state.pop(key)


def _with_prefix(module: BatchedNetwork, state: dict, prefix: str, *args) -> None:
    """``load_state_dict`` pre-hook: the keys :func:`_without_prefix` wrote go back to the wrapped network."""
    for key in [k for k in state if k.startswith(prefix)]:
        state[prefix + "net." + key[len(prefix) :]] = state.pop(key)


class BatchedPolicy:
    """``policy`` whose every ``act`` counts as one request in flight on ``batching`` (:meth:`BatchedNetwork.request`),
    so that a batch waits for exactly the callers that can still come and a lone caller does not wait. Everything
    else (``reset``, ``n_obs``, ``execute``, ...) is the policy's own."""

    def __init__(self, policy, batching: BatchedNetwork) -> None:
        self.policy, self.batching = policy, batching

    def reset(self, seed: int | None = None) -> None:
        self.policy.reset(seed)

    def act(self, obs: dict):
        with self.batching.request():
            return self.policy.act(obs)

    def __getattr__(self, name: str):
        if name in ("policy", "batching"):  # not set yet (copy, pickle): no recursion
            raise AttributeError(name)
        return getattr(self.policy, name)
