"""A denoising network run as TorchScript traces: the same outputs, less Python per call.

At the sizes K-CFM runs at on a CPU (one chunk of 16 actions, a (64, 128) U-Net) most of a network call is Python
dispatch, not arithmetic: ``torch.jit.trace`` records the call once and replays it as a graph, faster at batch 1
with outputs equal to eager (``results/export.md``). A trace is fixed to the
shapes it was recorded with, so :class:`TracedNetwork` keeps one per input signature (shapes, dtype, device) and
checks each against the eager network on the inputs it was recorded with; a trace that disagrees by more than
``atol`` (or that fails to record) is never used: that signature runs eagerly, as does every call of a network that
declares ``traceable = False`` (one that decides at run time what to run, e.g. the server's batching of several
threads' calls, :class:`~kpflow.serving.batching.BatchedNetwork`, which traces inside). The traces share the network's
parameters (no freezing), so loading or averaging weights into it later is seen by every trace.
"""

from __future__ import annotations

import threading
import warnings

import torch


class TracedNetwork:
    """``net(x, t, c)`` through per-signature TorchScript traces (module docstring).

    Args:
        net: the network (in eval mode); it is called as ``net(x, t, c)``.
        atol: the largest difference from the eager outputs a trace may show when it is recorded.
    """

    def __init__(self, net: torch.nn.Module, atol: float = 1e-5) -> None:
        self.net, self.atol = net, float(atol)
        self.eager = not getattr(net, "traceable", True)
        self.traces: dict[tuple, torch.jit.ScriptModule | None] = {}  # None: this signature runs eagerly
        self._lock = threading.Lock()

    @staticmethod
    def signature(*tensors: torch.Tensor) -> tuple:
        return tuple((tuple(x.shape), x.dtype, x.device) for x in tensors)

    def _record(self, x: torch.Tensor, t: torch.Tensor, c: torch.Tensor):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", torch.jit.TracerWarning)
                trace = torch.jit.trace(self.net, (x, t, c), check_trace=False)
            agree = (trace(x, t, c) - self.net(x, t, c)).abs().max().item() <= self.atol
        except RuntimeError:
            return None
        return trace if agree else None

    @torch.no_grad()
    def __call__(self, x: torch.Tensor, t: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        if self.eager:
            return self.net(x, t, c)
        t = torch.as_tensor(t, dtype=x.dtype, device=x.device)
        key = self.signature(x, t, c)
        if key not in self.traces:
            with self._lock:
                if key not in self.traces:
                    self.traces[key] = self._record(x, t.contiguous(), c)
        trace = self.traces[key]
        return self.net(x, t, c) if trace is None else trace(x, t.contiguous(), c)
