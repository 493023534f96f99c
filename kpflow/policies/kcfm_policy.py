"""A trained :class:`~kpflow.policies.kcfm.KCFM` behind the :class:`~kpflow.tasks.base.Policy` protocol.

``act(obs)`` samples one chunk for ``obs["keypoints"]`` (``obs["keypoints_history"] [n_obs, K, 2]`` for a model with an
observation history, as :func:`~kpflow.tasks.pusht.rollout.run_episode` provides) with ``steps`` network calls and
returns its first ``execute`` absolute agent targets (px). The flow's starting noise comes from a CPU ``torch.Generator`` seeded by
:meth:`KCFMPolicy.reset`, so an episode is reproducible from its seed (and does not depend on the model's device).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .kcfm import KCFM, MAX_STEPS


def check_steps_and_execute(model: KCFM, steps: int, execute: int) -> None:
    """Raise ``ValueError`` unless ``steps`` is in ``1..MAX_STEPS`` and ``execute`` in ``1..horizon``."""
    horizon = int(model.hparams.horizon)
    for name, value, hi in (("steps", steps, MAX_STEPS), ("execute", execute, horizon)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= hi:
            what = " (the model's chunk length)" if name == "execute" else ""
            raise ValueError(f"{name} must be an integer in 1..{hi}{what}; got {value!r}")


class KCFMPolicy:
    """K-CFM as a policy: ``act(obs) = model.sample(obs["keypoints"], steps, generator)[0, :execute]`` (float64).

    Args:
        model: a trained K-CFM (put in eval mode).
        steps: network calls per chunk (Euler steps of a flow, DDIM steps of a diffusion; ``1..MAX_STEPS``).
        execute: how many of the chunk's ``horizon`` actions :meth:`act` returns.
    """

    def __init__(self, model: KCFM, steps: int = 10, execute: int = 8) -> None:
        check_steps_and_execute(model, steps, execute)
        self.model, self.steps, self.execute = model.eval(), int(steps), int(execute)
        self.n_obs = int(model.hparams.n_obs)
        self.generator = torch.Generator()
        self.reset()

    @classmethod
    def from_checkpoint(cls, path: str | Path, steps: int = 10, execute: int = 8) -> "KCFMPolicy":
        """The policy of a K-CFM Lightning checkpoint, loaded on the CPU."""
        from kpflow.utils.checkpoint import load_checkpoint

        return cls(load_checkpoint(KCFM, path, map_location="cpu"), steps, execute)

    def reset(self, seed: int | None = None) -> None:
        """Reseed the sampling noise with ``seed`` (0 when None)."""
        self.generator = torch.Generator().manual_seed(0 if seed is None else int(seed))

    def act(self, obs: dict) -> np.ndarray:
        """The first ``execute`` actions ``[execute, A]`` of a chunk sampled for ``obs["keypoints"] [K, 2]`` (or
        ``obs["keypoints_history"] [n_obs, K, 2]``)."""
        if self.n_obs == 1:
            keypoints = obs["keypoints"]
        elif "keypoints_history" in obs:
            keypoints = obs["keypoints_history"]
        else:
            raise ValueError(f"this K-CFM conditions on the last {self.n_obs} observations: pass obs['keypoints_history'] [{self.n_obs}, K, 2]")
        chunk = self.model.sample(keypoints, self.steps, self.generator)
        return chunk[0, : self.execute].detach().to("cpu", torch.float64).numpy()
