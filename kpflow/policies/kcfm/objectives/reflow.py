"""Reflow: distilling a trained flow into few steps by training on its own noise-to-sample couplings (Liu, Gong &
Liu 2023, "Flow Straight and Fast: Learning to Generate and Transfer Data with Rectified Flow", Sec. 2.2 eq. 1 and
Alg. 1, the "2-rectified flow"; with the time restricted to a sampler's grid, its distillation step, Sec. 2.3).

A trained K-CFM, the *teacher* ``T``, maps noise to chunks deterministically: ``x1_hat = T(x0 | c)`` (its ODE solved
with ``teacher_steps`` calls of ``teacher_solver``). The student regresses the straight path of that coupling,

    x_t = t x1_hat + (1 - t) x0,        u_t = x1_hat - x0,        L = E || v(x_t, t, c) - u_t ||^2,

with ``x0 ~ N(0, I)`` drawn fresh for every batch. Where the teacher's paths are curved, many ``x0`` of different
chunks pass near the same ``x_t`` and the I-CFM field averages them, so a few Euler steps land between modes; the
teacher's own coupling does not cross (an ODE's trajectories never do), so its straight lines cross far less and a
few Euler steps, one at the end, follow them. ``t ~ U(0, 1)``, or, with ``t_grid = n``, ``t`` drawn from the grid
``{0, 1/n, .., (n-1)/n}`` where an ``n``-step Euler sampler calls the network (``t_grid = 1``: one-step
distillation, ``v(x0, 0, c) = x1_hat - x0``). The interpolant and its velocity are :func:`.paths.straight_path`;
sampling is :mod:`.icfm`'s.

The teacher is a checkpoint path in the options, read by :meth:`kpflow.policies.kcfm.KCFM.attach_teacher` when
training starts (never when a trained student is loaded): the student takes its normalisation and, with
``initialise``, its weights.
"""

from __future__ import annotations

from typing import Callable

import torch

from .base import TrainingTarget, identity_index, rand, randn_like
from .icfm import ICFM
from .paths import straight_path

#: ``T(x0, c) -> x1_hat``: the teacher's sampler in the normalised chunk space.
Teacher = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


class Reflow(ICFM):
    """Rectified-flow distillation of a teacher K-CFM (module docstring).

    Args:
        teacher: path of the teacher K-CFM's checkpoint.
        teacher_steps, teacher_solver: how the teacher samples (network calls, :mod:`.solvers` name).
        t_grid: None: ``t ~ U(0, 1)``; ``n``: ``t`` uniform on the ``n``-step Euler grid.
        initialise: start the student from the teacher's weights (the networks must match).
    """

    def __init__(
        self,
        teacher: str,
        teacher_steps: int = 10,
        teacher_solver: str = "midpoint",
        t_grid: int | None = None,
        initialise: bool = True,
    ) -> None:
        super().__init__()
        if not isinstance(teacher, str) or not teacher:
            raise ValueError(f"teacher must be the path of a trained K-CFM checkpoint; got {teacher!r}")
        if isinstance(teacher_steps, bool) or not isinstance(teacher_steps, int) or teacher_steps < 1:
            raise ValueError(f"teacher_steps must be an integer >= 1; got {teacher_steps!r}")
        if t_grid is not None and (isinstance(t_grid, bool) or not isinstance(t_grid, int) or t_grid < 1):
            raise ValueError(f"t_grid must be None or an integer >= 1; got {t_grid!r}")
        self.teacher, self.teacher_steps, self.teacher_solver = teacher, teacher_steps, teacher_solver
        self.t_grid, self.initialise = t_grid, bool(initialise)
        self._teacher: Teacher | None = None

    def attach(self, teacher: Teacher) -> None:
        """Give the objective the teacher's sampler ``T(x0, c)``."""
        self._teacher = teacher

    def times(self, n: int, like: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """``[n]`` training times: ``U(0, 1)``, or uniform on the ``t_grid``-step Euler grid."""
        u = rand(n, like, generator)
        return u if self.t_grid is None else torch.floor(u * self.t_grid) / self.t_grid

    def training_target(
        self, x1: torch.Tensor, cond: torch.Tensor | None = None, generator: torch.Generator | None = None, net=None
    ) -> TrainingTarget:
        if self._teacher is None:
            raise ValueError(
                f"reflow trains on its teacher's samples: attach the teacher first ({self.teacher}; KCFM.attach_teacher)"
            )
        x0 = randn_like(x1, generator)
        with torch.no_grad():
            x1_hat = self._teacher(x0, cond)
        t = self.times(len(x1), x1, generator)
        x_t, u_t = straight_path(x0, x1_hat, t)
        return TrainingTarget(x_t, t, u_t, identity_index(x1))
