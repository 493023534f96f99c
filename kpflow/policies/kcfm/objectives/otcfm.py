"""OT-CFM: conditional flow matching with minibatch optimal-transport couplings (Tong et al. 2024, "Improving and
generalizing flow-based generative models with minibatch optimal transport", Sec. 3.2, Alg. 2), made conditional
as in Kerrigan et al. 2024 ("Dynamic conditional optimal transport through simulation-free flows", Sec. 3).

Each noise row ``x0_i`` is given the condition ``c_i`` of its own batch row; the exact OT plan ``pi`` between the
pairs ``(x0_i, c_i)`` and ``(x1_j, c_j)`` under the cost

    C_ij = || x0_i - x1_j ||^2 + beta || c_i - c_j ||^2

is solved (POT's network simplex, ``ot.emd``, between uniform marginals on the two stacked vectors), ``B`` pairs
``(i, j)`` are drawn from ``pi`` with replacement (as Tong et al.'s Alg. 2 does), and as in I-CFM

    x_t = t x1_j + (1 - t) x0_i,     u_t = x1_j - x0_i,     L = E || v(x_t, t, c_j) - u_t ||^2.

The condition term is what keeps the noise of every condition standard normal: with ``beta = 0`` (Tong et al.'s
plain OT-CFM) a chunk's noise is the one nearest to it whatever its keypoints,
the network learns to stay near its starting noise, and at inference, from unmatched noise, it ignores the
condition (on Push-T it scored a fraction of I-CFM's: ``results/pusht_standard.md``, "OT-CFM needs its coupling to
respect the condition"). With a large ``beta`` rows are re-paired only
among near-identical conditions. The pairs are drawn with the objective's torch generator: training is reproducible.
"""

from __future__ import annotations

import numpy as np
import ot
import torch

from .icfm import ICFM


class OTCFM(ICFM):
    """Conditional minibatch-OT flow matching (module docstring).

    Args:
        condition_weight: ``beta``, the weight of the condition distance in the coupling's cost.
    """

    def __init__(self, condition_weight: float = 10.0) -> None:
        super().__init__()
        if not condition_weight >= 0:
            raise ValueError(f"condition_weight must be >= 0; got {condition_weight!r}")
        self.condition_weight = float(condition_weight)

    def pair(
        self, x0: torch.Tensor, x1: torch.Tensor, generator: torch.Generator | None, cond: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``B`` pairs ``(i, j) ~ pi`` with replacement: returns ``(x0[i], j)``."""
        a, b = x0.detach().flatten(1).float(), x1.detach().flatten(1).float()
        if cond is not None and self.condition_weight > 0:
            c = self.condition_weight**0.5 * cond.detach().flatten(1).float()
            a, b = torch.cat([a, c], 1), torch.cat([b, c], 1)
        pi = torch.as_tensor(exact_plan(a, b), dtype=torch.float64).flatten()
        draws = torch.multinomial(pi / pi.sum(), len(x1), replacement=True, generator=_cpu(generator))
        i, j = draws // len(x1), draws % len(x1)
        return x0[i.to(x0.device)], j.to(x1.device)


def exact_plan(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    """The exact OT plan ``[B, B]`` between the rows of ``a`` and ``b`` (uniform marginals) under the squared Euclidean
    cost (POT's ``emd``); a plan that lost its mass to round-off is replaced by the uniform one."""
    cost = (torch.cdist(a, b) ** 2).cpu().numpy()
    pi = ot.emd(ot.unif(len(a)), ot.unif(len(b)), cost)
    return pi if np.abs(pi.sum()) >= 1e-8 else np.full_like(pi, 1.0 / pi.size)


def _cpu(generator: torch.Generator | None) -> torch.Generator | None:
    """multinomial draws on the CPU: a generator on another device cannot be used (None then: the global one)."""
    return generator if generator is None or generator.device.type == "cpu" else None
