"""OT-CFM: conditional flow matching with minibatch optimal-transport couplings (Tong et al. 2024, "Improving and
generalizing flow-based generative models with minibatch optimal transport", Sec. 3.2, Alg. 2).

Per batch, the exact OT plan ``pi`` between the noise rows ``x0_i`` and the data rows ``x1_j`` under the squared
Euclidean cost is solved (torchcfm's ``OTPlanSampler("exact")``, POT's network simplex); ``B`` pairs ``(i, j)``
are drawn from ``pi`` with replacement (as torchcfm does); then, as in I-CFM,

    x_t = t x1_j + (1 - t) x0_i,     u_t = x1_j - x0_i,     L = E || v(x_t, t, c_j) - u_t ||^2,

so each pair keeps its data row's condition and mask. Straighter paths than independent pairs: fewer integration
steps for the same error. The pairs are drawn with the objective's torch generator, so training is reproducible.
"""

from __future__ import annotations

import torch
from torchcfm.optimal_transport import OTPlanSampler

from .icfm import ICFM


class OTCFM(ICFM):
    """Minibatch-OT conditional flow matching (module docstring)."""

    def __init__(self) -> None:
        super().__init__()
        self.plan = OTPlanSampler(method="exact")

    def pair(self, x0: torch.Tensor, x1: torch.Tensor, generator: torch.Generator | None) -> tuple[torch.Tensor, torch.Tensor]:
        """``B`` pairs ``(i, j) ~ pi`` with replacement: returns ``(x0[i], j)``."""
        pi = torch.as_tensor(self.plan.get_map(x0.detach().float(), x1.detach().float()), dtype=torch.float64).flatten()
        draws = torch.multinomial(pi / pi.sum(), len(x1), replacement=True, generator=_cpu(generator))
        i, j = draws // len(x1), draws % len(x1)
        return x0[i.to(x0.device)], j.to(x1.device)


def _cpu(generator: torch.Generator | None) -> torch.Generator | None:
    """multinomial draws on the CPU: a generator on another device cannot be used (None then: the global one)."""
    return generator if generator is None or generator.device.type == "cpu" else None
