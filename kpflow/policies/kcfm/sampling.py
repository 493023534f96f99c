"""How a K-CFM samples a chunk: at most :data:`MAX_STEPS` network calls of one of its objective's solvers."""

from __future__ import annotations

import numpy as np

MAX_STEPS = 100  # most network calls :meth:`KCFM.sample` takes (solver steps of a flow, DDIM steps of a diffusion)


def check_sampler(objective, steps, solver: str | None) -> None:
    """Raise ``ValueError`` unless ``steps`` is an integer in ``1..MAX_STEPS`` and ``solver`` is None or one of the
    ``objective``'s samplers."""
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or not 1 <= steps <= MAX_STEPS:
        raise ValueError(f"steps must be an integer in 1..{MAX_STEPS} (network calls per chunk); got {steps!r}")
    if solver is not None and solver not in objective.solvers:
        raise ValueError(
            f"solver must be one of {objective.solvers} for this objective ({type(objective).__name__}); got {solver!r}"
        )


# -------------------------------------------------------------------------------------------- goal frame
