"""K-CFM: keypoint-conditioned flow matching of action chunks.

A policy ``pi(a_{t:t+H} | k_t)`` that generates a chunk of ``H`` absolute agent targets (px) from the 25 Push-T
keypoints ``k_t`` (block T, goal T, agent; see :mod:`kpflow.tasks.pusht.geometry`) by integrating a learned
velocity field from Gaussian noise (``t = 0``) to an action chunk (``t = 1``).

Training is conditional flow matching with the optimal-transport path and ``sigma_min = 0`` (Lipman et al. 2023,
"Flow Matching for Generative Modeling", Sec. 4.1, eqs. 20-23; torchcfm's ``ConditionalFlowMatcher(sigma=0)``,
the I-CFM of Tong et al. 2024): with ``x0 ~ N(0, I)``, ``x1`` a normalised data chunk and ``t ~ U(0, 1)``,

    x_t = t x1 + (1 - t) x0,        u_t(x_t | x0, x1) = x1 - x0,
    L(theta) = E || v_theta(x_t, t, c) - u_t ||^2        (averaged over the real, unpadded steps of the chunk).

Sampling solves ``dx/dt = v_theta(x, t, c)`` (Lipman et al. eq. 1) with ``steps`` explicit Euler steps.

The velocity network is :class:`~kpflow.policies.unet1d.ConditionalUnet1D`; the condition ``c`` is the 25
keypoints, flattened and standardised, optionally first expressed in the frame of the goal T (``goal_frame=True``:
then the policy is equivariant to rotating and translating the whole scene by construction). Actions are expressed
in the *action frame* of their observation: the goal's (``goal_frame``), moved to the agent (``relative=True``: a
chunk is then the agent's offsets from where it stands, so its first targets start next to the agent whatever the
scene), and scaled to [-1, 1] per dimension by their training min/max over every step of the chunks (as in
Diffusion Policy). All statistics live in buffers and an
exponential moving average of the weights is kept beside them, so a checkpoint is all a deployment needs:
``load_checkpoint(KCFM, path).sample(keypoints)``.
"""

from __future__ import annotations

import copy
import math
from typing import Sequence

import lightning
import numpy as np
import torch

from kpflow.policies.unet1d import ConditionalUnet1D
from kpflow.tasks.pusht.geometry import N_KEYPOINTS, N_T_KEYPOINTS, T_KEYPOINTS

MAX_STEPS = 10  # most Euler steps :meth:`KCFM.sample` takes
LR_SCHEDULES = ("cosine", "constant")
GOAL_SLICE = slice(N_T_KEYPOINTS, 2 * N_T_KEYPOINTS)  # the goal T's 12 keypoints among the 25
_MIN_STD = 1e-3  # px: a keypoint coordinate with a smaller spread (e.g. a fixed goal) is centred but not scaled
_MIN_HALF_RANGE = 1e-6  # an action dimension with a smaller range is centred but not scaled


# ------------------------------------------------------------------------------------------- flow matching


def interpolate(x0: torch.Tensor, x1: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """The conditional flow ``x_t = psi_t(x0) = t x1 + (1 - t) x0`` (Lipman et al. 2023, eq. 22 with
    ``sigma_min = 0``; torchcfm ``ConditionalFlowMatcher.compute_mu_t`` with ``sigma = 0``).

    ``t`` is a scalar or one time per batch item ``[B]``, broadcast over the trailing dims of ``x0``/``x1``.
    """
    t = torch.as_tensor(t, dtype=x0.dtype, device=x0.device)
    if t.ndim == 1:
        t = t.reshape(-1, *(1,) * (x0.ndim - 1))
    return t * x1 + (1 - t) * x0


def target_velocity(x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
    """The conditional velocity ``u_t(x_t | x0, x1) = d/dt psi_t(x0) = x1 - x0``, constant in ``t``
    (Lipman et al. 2023, the regression target of eq. 23 with ``sigma_min = 0``)."""
    return x1 - x0


def masked_mse(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the steps where ``mask`` is True.

    ``pred, target [B, H, A]``, ``mask [B, H]`` (bool): ``sum_{b,h} m_bh ||pred_bh - target_bh||^2 / (A sum m)``;
    0 when no step is real. Masked-out steps contribute nothing, whatever their values (even NaN).
    """
    m = mask.to(pred.dtype)
    err = torch.where(mask[..., None], pred - target, torch.zeros((), dtype=pred.dtype, device=pred.device))
    return err.square().mean(-1).mul(m).sum() / m.sum().clamp_min(1.0)


def fill_padding(actions: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``actions [B, H, A]`` with each masked-out step replaced by the latest real step before it (the first real
    step if none comes before), which is how :class:`~kpflow.data.chunks.ChunkDataset` pads past an episode's
    end. So the values stored at padded steps never reach the network: together with :func:`masked_mse`,
    padding does not affect training at all."""
    h = torch.arange(mask.shape[-1], device=mask.device).expand_as(mask)
    first = mask.to(torch.int64).argmax(-1, keepdim=True).expand_as(mask)
    idx = torch.where(mask, h, -1).cummax(-1).values
    idx = torch.where(idx < 0, first, idx)
    return actions.gather(1, idx[..., None].expand_as(actions))


# -------------------------------------------------------------------------------------------- goal frame


def goal_pose(goal_keypoints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid pose ``(R [..., 2, 2], p [..., 2])`` of a T from its 12 keypoints ``[..., 12, 2]``.

    The 2-D Kabsch (orthogonal Procrustes) fit ``min_{R in SO(2), p} sum_i ||R k_i + p - g_i||^2`` against the body
    keypoints ``k_i`` (:data:`~kpflow.tasks.pusht.geometry.T_KEYPOINTS`): with centred ``k~_i``, ``g~_i``,
    ``theta = atan2(sum_i k~_i x g~_i, sum_i k~_i . g~_i)``, ``R = R(theta)``, ``p = mean(g) - R mean(k)``.
    Exact for the keypoints of a T at any pose (``p, theta`` are the pose's ``x, y, theta``).
    """
    body = torch.as_tensor(T_KEYPOINTS, dtype=goal_keypoints.dtype, device=goal_keypoints.device)
    kc = body - body.mean(0)
    g_mean = goal_keypoints.mean(-2)
    gc = goal_keypoints - g_mean[..., None, :]
    cross = (kc[:, 0] * gc[..., 1] - kc[:, 1] * gc[..., 0]).sum(-1)
    dot = (kc * gc).sum((-1, -2))
    theta = torch.atan2(cross, dot)
    c, s = theta.cos(), theta.sin()
    rot = torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)
    return rot, g_mean - body.mean(0) @ rot.mT


def to_frame(points: torch.Tensor, rot: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:
    """World points ``[B, N, 2]`` into the frame ``(R [B, 2, 2], p [B, 2])``: ``R^T (x - p)`` (like ``geometry.to_body``)."""
    return (points - origin[:, None]) @ rot


def from_frame(points: torch.Tensor, rot: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:
    """Frame points ``[B, N, 2]`` back to the world: ``R q + p`` (the inverse of :func:`to_frame`)."""
    return points @ rot.mT + origin[:, None]


def _float64(x) -> torch.Tensor:
    """An array-like or tensor (any device) as a float64 CPU tensor."""
    if isinstance(x, torch.Tensor):
        return x.detach().to("cpu", torch.float64)
    return torch.as_tensor(np.asarray(x, dtype=np.float64))


# ------------------------------------------------------------------------------------------------ policy


class KCFM(lightning.LightningModule):
    """Keypoint-conditioned flow matching policy for action chunks (see the module docstring).

    Args:
        horizon: chunk length ``H`` (must match the datamodule's).
        n_keypoints: keypoints per observation (25 for Push-T).
        action_dim: size of one action (2: an absolute agent target in px).
        goal_frame: express keypoints and actions in the frame of the goal T (keypoints 12..23), fitted by
            :func:`goal_pose`; predictions are mapped back to the world. Needs the Push-T layout (25 keypoints,
            2-D actions).
        relative: predict actions as offsets from the agent, the last keypoint (in the goal's axes with
            ``goal_frame``). Needs 2-D actions.
        down_dims, kernel_size, n_groups, time_dim: the :class:`~kpflow.policies.unet1d.ConditionalUnet1D`.
        lr, weight_decay: AdamW.
        lr_schedule: ``"cosine"`` (to 0 over the trainer's ``estimated_stepping_batches``) or ``"constant"``.
        warmup_steps: linear LR warm-up before the schedule.
        ema_decay: decay of the exponential moving average of the weights; the decay used at optimizer step
            ``n`` is ``min(ema_decay, (1 + n) / (10 + n))`` so the average forgets its random start quickly.
    """

    def __init__(
        self,
        horizon: int = 20,
        n_keypoints: int = N_KEYPOINTS,
        action_dim: int = 2,
        goal_frame: bool = False,
        relative: bool = False,
        down_dims: Sequence[int] = (32, 64),
        kernel_size: int = 5,
        n_groups: int = 8,
        time_dim: int = 64,
        lr: float = 1e-3,
        weight_decay: float = 1e-6,
        lr_schedule: str = "cosine",
        warmup_steps: int = 0,
        ema_decay: float = 0.999,
    ) -> None:
        super().__init__()
        if horizon < 1 or n_keypoints < 1 or action_dim < 1:
            raise ValueError(f"need horizon, n_keypoints, action_dim >= 1; got {horizon}, {n_keypoints}, {action_dim}")
        if goal_frame and (n_keypoints != N_KEYPOINTS or action_dim != 2):
            raise ValueError(f"goal_frame needs the Push-T layout ({N_KEYPOINTS} keypoints, 2-D actions); got {n_keypoints}, {action_dim}")
        if relative and action_dim != 2:
            raise ValueError(f"relative actions are offsets from the agent keypoint: they need 2-D actions; got {action_dim}")
        if lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}; got {lr_schedule!r}")
        if not 0.0 <= ema_decay < 1.0:
            raise ValueError(f"ema_decay must be in [0, 1); got {ema_decay}")
        if warmup_steps < 0:
            raise ValueError(f"warmup_steps must be >= 0; got {warmup_steps}")
        self.save_hyperparameters()
        self.net = ConditionalUnet1D(action_dim, 2 * n_keypoints, tuple(down_dims), kernel_size, n_groups, time_dim)
        self.ema_net = copy.deepcopy(self.net).requires_grad_(False)
        self.register_buffer("kp_mean", torch.zeros(2 * n_keypoints))
        self.register_buffer("kp_std", torch.ones(2 * n_keypoints))
        self.register_buffer("action_center", torch.zeros(action_dim))
        self.register_buffer("action_scale", torch.ones(action_dim))
        self.register_buffer("stats_set", torch.tensor(False))

    # ------------------------------------------------------------------------------------ normalisation

    def set_normalisation(self, keypoints, chunks, mask=None) -> None:
        """Fit the statistics to world-frame ``keypoints [N, K, 2]`` and their action ``chunks [N, H, A]`` (or single
        actions ``[N, A]``), counting only the steps where ``mask [N, H]`` is true (all when None).

        Keypoints (in the goal frame if ``goal_frame``) are standardised per coordinate; a coordinate with a spread
        under 1e-3 px is only centred. Actions (in their row's action frame, see :meth:`action_frame`) are mapped
        to [-1, 1] per dimension by their min/max.
        """
        kp, act = _float64(keypoints), _float64(chunks)
        k, a = self.hparams.n_keypoints, self.hparams.action_dim
        if act.ndim == 2:
            act = act[:, None]
        if kp.ndim != 3 or kp.shape[1:] != (k, 2) or act.ndim != 3 or act.shape[::2] != (len(kp), a) or len(kp) == 0:
            raise ValueError(
                f"need keypoints [N, {k}, 2] and actions [N, {a}] or [N, H, {a}] with N >= 1; "
                f"got {tuple(kp.shape)} and {tuple(_float64(chunks).shape)}"
            )
        mask = torch.ones(act.shape[:2], dtype=torch.bool) if mask is None else torch.as_tensor(np.asarray(mask)).bool()
        if mask.shape != act.shape[:2] or not mask.any():
            raise ValueError(f"mask must be [N, H] = {tuple(act.shape[:2])} with a true entry; got {tuple(mask.shape)}")
        for name, x in (("keypoints", kp), ("actions", act)):
            bad = ~torch.isfinite(x).reshape(len(x), -1).all(-1)
            if bad.any():
                raise ValueError(f"training {name} contain NaN or inf (rows {torch.nonzero(bad).flatten()[:10].tolist()})")
        frame = self.action_frame(kp)
        if frame is not None:
            act = to_frame(act, *frame)
        if self.hparams.goal_frame:
            kp = to_frame(kp, *goal_pose(kp[:, GOAL_SLICE]))
        flat = kp.reshape(len(kp), -1)
        std = flat.std(0, unbiased=False)
        real = act[mask]
        lo, hi = real.min(0).values, real.max(0).values
        half = (hi - lo) / 2
        with torch.no_grad():
            self.kp_mean.copy_(flat.mean(0))
            self.kp_std.copy_(torch.where(std < _MIN_STD, torch.ones_like(std), std))
            self.action_center.copy_((hi + lo) / 2)
            self.action_scale.copy_(torch.where(half < _MIN_HALF_RANGE, torch.ones_like(half), half))
            self.stats_set.fill_(True)

    def setup(self, stage: str) -> None:
        """Fit the normalisation to ``trainer.datamodule.train_set`` (once; a resumed run keeps the checkpoint's)."""
        if stage != "fit" or self.trainer is None or bool(self.stats_set):
            return
        ds = getattr(self.trainer.datamodule, "train_set", None)
        if ds is None:
            raise ValueError(
                "KCFM takes its normalisation from trainer.datamodule.train_set: fit it with datamodule=ChunkDataModule(...) "
                "or call set_normalisation() first"
            )
        if getattr(ds, "horizon", self.hparams.horizon) != self.hparams.horizon:
            raise ValueError(f"the data's chunk horizon {ds.horizon} differs from the model's horizon={self.hparams.horizon}")
        obs, chunks, mask = ds.arrays()  # one row per step of the training episodes only
        self.set_normalisation(obs, chunks, mask)

    def _condition(self, keypoints: torch.Tensor) -> torch.Tensor:
        """Condition ``c [B, 2K]`` (float32) of world keypoints ``[B, K, 2]``: in the goal frame if ``goal_frame``."""
        kp = keypoints.to(torch.float64)
        if self.hparams.goal_frame:
            kp = to_frame(kp, *goal_pose(kp[:, GOAL_SLICE]))
        return ((kp.flatten(1) - self.kp_mean.double()) / self.kp_std.double()).float()

    def action_frame(self, keypoints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The rigid frame ``(R [B, 2, 2], p [B, 2])`` that actions are predicted in, for keypoints ``[B, K, 2]``.

        ``R`` is the goal's rotation with ``goal_frame`` (else the identity), ``p`` the agent (the last keypoint) with
        ``relative`` (else the goal's origin, or 0). None when both are off: actions stay in world coordinates.
        """
        hp = self.hparams
        if not (hp.goal_frame or hp.relative):
            return None
        kp = keypoints.to(torch.float64)
        if hp.goal_frame:
            rot, origin = goal_pose(kp[:, GOAL_SLICE])
        else:
            rot, origin = torch.eye(2, dtype=kp.dtype, device=kp.device).expand(len(kp), 2, 2), torch.zeros_like(kp[:, 0])
        return rot, kp[:, -1] if hp.relative else origin

    def normalise_actions(self, actions: torch.Tensor, frame=None) -> torch.Tensor:
        """World actions ``[B, H, A]`` to the network's space: into the action ``frame`` (if given), then to [-1, 1]."""
        a = actions.to(torch.float64)
        if frame is not None:
            a = to_frame(a, *frame)
        return ((a - self.action_center.double()) / self.action_scale.double()).float()

    def denormalise_actions(self, x: torch.Tensor, frame=None) -> torch.Tensor:
        """The inverse of :meth:`normalise_actions`: network-space chunks ``[B, H, A]`` to world actions (float32)."""
        a = x.to(torch.float64) * self.action_scale.double() + self.action_center.double()
        if frame is not None:
            a = from_frame(a, *frame)
        return a.float()

    # ----------------------------------------------------------------------------------------- training

    def _randn(self, shape, generator: torch.Generator | None) -> torch.Tensor:
        device = generator.device if generator is not None else self.device
        return torch.randn(shape, generator=generator, device=device).to(self.device)

    def _rand(self, shape, generator: torch.Generator | None) -> torch.Tensor:
        device = generator.device if generator is not None else self.device
        return torch.rand(shape, generator=generator, device=device).to(self.device)

    def loss(
        self,
        batch: dict,
        net: torch.nn.Module | None = None,
        x0: torch.Tensor | None = None,
        t: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """The masked conditional flow-matching loss of a :class:`~kpflow.data.chunks.ChunkDataset` batch.

        ``L = masked_mse(v(x_t, t, c), x1 - x0, mask)`` with ``x_t = t x1 + (1 - t) x0`` (module docstring),
        ``x1`` the normalised chunk (padding filled by :func:`fill_padding`), ``x0 ~ N(0, I)`` and ``t ~ U(0, 1)``
        drawn with ``generator`` unless given. ``net`` defaults to the trained (non-EMA) network.
        """
        kp, actions, mask = batch["obs"], batch["actions"], batch["mask"]
        k, h, a = self.hparams.n_keypoints, self.hparams.horizon, self.hparams.action_dim
        b = len(kp)
        if kp.shape != (b, k, 2) or actions.shape != (b, h, a) or mask.shape != (b, h):
            raise ValueError(
                f"batch must hold obs [B, {k}, 2], actions [B, {h}, {a}] and mask [B, {h}]; "
                f"got {tuple(kp.shape)}, {tuple(actions.shape)}, {tuple(mask.shape)}"
            )
        c = self._condition(kp)
        x1 = self.normalise_actions(fill_padding(actions, mask.bool()), self.action_frame(kp))
        x0 = self._randn(x1.shape, generator) if x0 is None else x0
        t = self._rand(b, generator) if t is None else t
        net = self.net if net is None else net
        return masked_mse(net(interpolate(x0, x1, t), t, c), target_velocity(x0, x1), mask.bool())

    def training_step(self, batch, batch_idx: int) -> torch.Tensor:
        loss = self.loss(batch)
        self.log("train/loss", loss, prog_bar=True, batch_size=len(batch["obs"]))
        return loss

    def validation_step(self, batch, batch_idx: int) -> None:
        # EMA weights, and noise fixed per batch so that the validation loss compares across epochs.
        generator = torch.Generator(device=self.device).manual_seed(batch_idx)
        self.log("val/loss", self.loss(batch, net=self.ema_net, generator=generator), prog_bar=True, batch_size=len(batch["obs"]))

    @torch.no_grad()
    def on_train_batch_end(self, outputs, batch, batch_idx: int) -> None:
        """EMA update ``theta_ema <- d theta_ema + (1 - d) theta`` with ``d = min(ema_decay, (1 + n) / (10 + n))``."""
        n = self.global_step
        decay = min(self.hparams.ema_decay, (1 + n) / (10 + n))
        for ema, p in zip(self.ema_net.parameters(), self.net.parameters()):
            ema.lerp_(p, 1.0 - decay)

    def configure_optimizers(self):
        hp = self.hparams
        opt = torch.optim.AdamW(self.net.parameters(), lr=hp.lr, weight_decay=hp.weight_decay)
        if hp.lr_schedule == "constant" and hp.warmup_steps == 0:
            return opt
        total = self.trainer.estimated_stepping_batches if hp.lr_schedule == "cosine" else math.inf
        if hp.lr_schedule == "cosine" and not math.isfinite(total):
            raise ValueError("the cosine LR schedule needs a finite run: set the trainer's max_steps or max_epochs")
        warm = hp.warmup_steps

        def factor(step: int) -> float:
            if step < warm:
                return (step + 1) / warm
            if hp.lr_schedule == "constant":
                return 1.0
            return 0.5 * (1.0 + math.cos(math.pi * min(1.0, (step - warm) / max(1, total - warm))))

        scheduler = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    # ---------------------------------------------------------------------------------------- inference

    def _check_keypoints(self, keypoints) -> torch.Tensor:
        """``keypoints [K, 2]`` or ``[B, K, 2]`` as a finite float64 tensor ``[B, K, 2]`` on the model's device."""
        if isinstance(keypoints, torch.Tensor):
            kp = keypoints
            if kp.is_complex() or kp.dtype == torch.bool:
                raise ValueError(f"keypoints must be real numbers; got dtype {kp.dtype}")
        else:
            try:
                kp = torch.as_tensor(np.asarray(keypoints, dtype=np.float64))
            except (TypeError, ValueError) as e:
                raise ValueError(f"keypoints must be an array of numbers ({e})") from e
        k, shape = self.hparams.n_keypoints, tuple(kp.shape)
        if kp.ndim == 2:
            kp = kp[None]
        if kp.ndim != 3 or kp.shape[1:] != (k, 2) or len(kp) == 0:
            raise ValueError(f"keypoints must have shape [{k}, 2] or [B, {k}, 2] with B >= 1; got {shape}")
        kp = kp.to(self.device, torch.float64)
        bad = ~torch.isfinite(kp).reshape(len(kp), -1).all(-1)
        if bad.any():
            raise ValueError(f"keypoints contain NaN or inf (batch items {torch.nonzero(bad).flatten()[:10].tolist()})")
        return kp

    @torch.no_grad()
    def sample(self, keypoints, steps: int = 10, generator: torch.Generator | None = None) -> torch.Tensor:
        """Action chunks ``[B, H, A]`` (float32, world px) for keypoints ``[B, K, 2]`` or ``[K, 2]`` (then ``B = 1``).

        Euler integration of ``dx/dt = v_ema(x, t, c)`` from ``x(0) ~ N(0, I)`` (drawn with ``generator``, on the
        generator's device) to ``t = 1`` in ``steps`` equal steps ``x <- x + v(x, k / steps, c) / steps``, with the
        EMA weights. Deterministic given the generator's state.

        Raises:
            ValueError: ``steps`` not an integer in ``1..MAX_STEPS``; keypoints of the wrong shape or not finite.
        """
        if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or not 1 <= steps <= MAX_STEPS:
            raise ValueError(f"steps must be an integer in 1..{MAX_STEPS}; got {steps!r}")
        kp = self._check_keypoints(keypoints)
        c, frame = self._condition(kp), self.action_frame(kp)
        b = len(kp)
        x = self._randn((b, self.hparams.horizon, self.hparams.action_dim), generator)
        dt = 1.0 / int(steps)
        for i in range(int(steps)):
            x = x + dt * self.ema_net(x, torch.full((b,), i * dt, device=self.device), c)
        return self.denormalise_actions(x, frame)

    def forward(self, keypoints, steps: int = 10, generator: torch.Generator | None = None) -> torch.Tensor:
        """Same as :meth:`sample`."""
        return self.sample(keypoints, steps, generator)
