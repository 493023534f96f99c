"""Fixed-step ODE solvers for ``dx/dt = v(x, t)`` from ``t = 0`` to 1, counted in network calls.

Every solver takes a budget of ``calls`` evaluations of ``v`` (the unit every objective is compared in) and splits
[0, 1] into equal intervals of length ``h``:

- ``euler`` (first order): ``calls`` intervals, ``x <- x + h v(x, t)``.
- ``midpoint`` (explicit midpoint rule, second order; Hairer, Norsett & Wanner, "Solving Ordinary Differential
  Equations I", Sec. II.1, eq. 1.5): two calls per interval,
  ``x <- x + h v(x + (h/2) v(x, t), t + h/2)``.
- ``heun`` (explicit trapezoidal rule, second order; ibid., Table 1.1): two calls per interval,
  ``k1 = v(x, t)``, ``k2 = v(x + h k1, t + h)``, ``x <- x + (h/2) (k1 + k2)``.

A second-order solver with an odd budget ends with one Euler interval of the same length (one call: plain Euler).
The local error of the second-order rules is ``O(h^3)`` against Euler's ``O(h^2)``: halving ``h`` divides the
global error by about 4 instead of 2 (tests/test_objectives.py checks it on ``dx/dt = a x``).
"""

from __future__ import annotations

import torch

from .base import Denoiser

SOLVERS = ("euler", "midpoint", "heun")


def intervals(calls: int, solver: str) -> list[str]:
    """The rule of each equal interval that ``calls`` network calls of ``solver`` buy (see the module docstring)."""
    if solver not in SOLVERS:
        raise ValueError(f"unknown ODE solver {solver!r}; choose one of {SOLVERS}")
    if isinstance(calls, bool) or not isinstance(calls, int) or calls < 1:
        raise ValueError(f"network calls must be an integer >= 1; got {calls!r}")
    if solver == "euler":
        return ["euler"] * calls
    return [solver] * (calls // 2) + ["euler"] * (calls % 2)


def integrate(net: Denoiser, x: torch.Tensor, calls: int, solver: str = "euler") -> torch.Tensor:
    """``x(1)`` of ``dx/dt = net(x, t)`` from ``x(0) = x`` with ``calls`` evaluations of ``net`` (module docstring)."""
    rules = intervals(calls, solver)
    h = 1.0 / len(rules)

    def time(t: float) -> torch.Tensor:
        return torch.full((len(x),), t, device=x.device, dtype=x.dtype)

    for k, rule in enumerate(rules):
        t = k * h
        v = net(x, time(t))
        if rule == "euler":
            x = x + h * v
        elif rule == "midpoint":
            x = x + h * net(x + 0.5 * h * v, time(t + 0.5 * h))
        else:  # heun
            x = x + 0.5 * h * (v + net(x + h * v, time(t + h)))
    return x
