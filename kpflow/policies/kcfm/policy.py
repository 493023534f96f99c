"""A trained :class:`~kpflow.policies.kcfm.KCFM` behind the :class:`~kpflow.core.task.Policy` protocol.

``act(obs)`` samples one chunk for ``obs["keypoints"]`` (``obs["keypoints_history"] [n_obs, K, 2]`` for a model with an
observation history, as :func:`~kpflow.tasks.pusht.rollout.run_episode` provides) with ``steps`` network calls of
``solver`` (by default the checkpoint's own, :meth:`KCFM.sampler`) and returns its first ``execute`` absolute agent targets (px). The flow's starting noise comes from a CPU ``torch.Generator`` seeded by
:meth:`KCFMPolicy.reset`, so an episode is reproducible from its seed (and does not depend on the model's device).

An observation far outside the training data (farther outside its keypoints' box than ``input_margin`` times the
box's extent, :meth:`KCFM.check_in_range`) is refused before the network runs, and actions that are not finite are
never returned (:func:`~kpflow.policies.checks.check_actions`): both raise a ``ValueError`` naming the cause.
"""

from __future__ import annotations

import weakref

import numpy as np
import torch

from kpflow.utils.config_checks import RESET_SEED, Key

from ..checks import INPUT_MARGIN, check_actions
from .model import KCFM
from .traced import TracedNetwork

_INPUT_MARGIN = Key(float, lo=0, nullable=True)


_TRACES: "weakref.WeakKeyDictionary[KCFM, TracedNetwork]" = weakref.WeakKeyDictionary()


def traced_network(model: KCFM) -> TracedNetwork:
    """The model's EMA network as traces, one :class:`~.traced.TracedNetwork` per model and network (the policies
    of one deployment share its traces; a model whose ``ema_net`` was replaced gets new ones)."""
    traced = _TRACES.get(model)
    if traced is None or traced.net is not model.ema_net:
        traced = _TRACES[model] = TracedNetwork(model.ema_net)
    return traced


def check_steps_and_execute(model: KCFM, steps: int | None, execute: int | None, solver: str | None = None) -> int:
    """Raise ``ValueError`` unless ``steps`` (None: the model's) and ``solver`` suit the model's objective
    (:meth:`KCFM.sampler`) and ``execute`` (None: the checkpoint's setting, else 8) is in ``1..horizon``; returns
    ``execute``."""
    model.sampler(steps, solver)
    execute = model.settings.actions if execute is None else execute
    horizon = int(model.hparams.horizon)
    if isinstance(execute, bool) or not isinstance(execute, (int, np.integer)) or not 1 <= execute <= horizon:
        raise ValueError(f"execute must be an integer in 1..{horizon} (the model's chunk length); got {execute!r}")
    return int(execute)


class KCFMPolicy:
    """K-CFM as a policy: ``act(obs) = model.sample(obs["keypoints"], steps, generator, solver)[0, :execute]`` (float64).

    Args:
        model: a trained K-CFM (put in eval mode).
        steps: network calls per chunk (solver steps of a flow, DDIM steps of a diffusion; ``1..MAX_STEPS``); None:
            the checkpoint's setting, else the model's ``sampler.steps``.
        execute: how many of the chunk's ``horizon`` actions :meth:`act` returns (None: the checkpoint's setting,
            :mod:`~kpflow.policies.settings`, else 8).
        input_margin: how far outside the training keypoints' box an observed coordinate may lie, in extents of the
            box on each side (:meth:`KCFM.check_in_range`; >= 0); None: no range check.
        solver: the objective's sampler (``euler``, ``midpoint``, ``heun``; ``ddim``); None: the model's.
        trace: run the network as TorchScript traces (:class:`~.traced.TracedNetwork`: the same outputs, less time
            per call at batch 1, ``results/export.md``); False: eagerly.
    """

    def __init__(self, model: KCFM, steps: int | None = None, execute: int | None = None, input_margin: float | None = INPUT_MARGIN,
                 solver: str | None = None, trace: bool = True) -> None:  # fmt: skip
        execute = check_steps_and_execute(model, steps, execute, solver)
        _INPUT_MARGIN.check("input_margin", input_margin)
        self.steps, self.solver = model.sampler(steps, solver)
        self.model, self.execute = model.eval(), int(execute)
        self.network = traced_network(model) if trace else model.ema_net
        self.input_margin = None if input_margin is None else float(input_margin)
        self.n_obs = int(model.hparams.n_obs)
        self.generator = torch.Generator()
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        """Reseed the sampling noise with ``seed`` (an integer >= 0; 0 when None)."""
        RESET_SEED.check("seed", seed)
        self.generator = torch.Generator().manual_seed(0 if seed is None else int(seed))

    def act(self, obs: dict) -> np.ndarray:
        """The first ``execute`` actions ``[execute, A]`` of a chunk sampled for ``obs["keypoints"] [K, 2]`` (or
        ``obs["keypoints_history"] [n_obs, K, 2]``).

        Raises:
            ValueError: keypoints of the wrong shape, not finite or far outside the training data
                (:meth:`KCFM.check_in_range`); actions that came out NaN or inf.
        """
        if self.n_obs == 1:
            keypoints = obs["keypoints"]
        elif "keypoints_history" in obs:
            keypoints = obs["keypoints_history"]
        else:
            raise ValueError(
                f"this K-CFM conditions on the last {self.n_obs} observations: pass obs['keypoints_history'] [{self.n_obs}, K, 2]"
            )
        chunk = self.model.sample(keypoints, self.steps, self.generator, self.solver, self.network, self.input_margin)
        return check_actions(chunk[0, : self.execute].detach().to("cpu", torch.float64).numpy(), "the K-CFM")
