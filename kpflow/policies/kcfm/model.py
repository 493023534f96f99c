"""K-CFM: keypoint-conditioned generative policy of action chunks.

A policy ``pi(a_{t:t+H} | k_{t-n+1..t})`` that generates a chunk of ``H`` actions (e.g. absolute agent targets) from
the last ``n_obs`` observations of a task's ``K`` keypoints ``k`` (Push-T: 25, block T, goal T and agent,
:mod:`kpflow.tasks.pusht.geometry`) by denoising Gaussian noise with a conditional network.

The generative objective is injected by name (:mod:`kpflow.policies.kcfm.objectives`): ``"icfm"`` (conditional flow
matching, the straight path with ``sigma = 0``: Lipman et al. 2023 eqs. 20-23, the default), ``"otcfm"`` (with
minibatch optimal-transport couplings, Tong et al. 2024), ``"ddpm"`` (DDPM training and DDIM sampling as Diffusion
Policy does it: with the same network, data and budget, the DP-equivalent baseline), ``"meanflow"`` (average
velocities, one step from noise to data, Geng et al. 2025) or ``"reflow"`` (distillation of a trained K-CFM, the
*teacher*, into few steps: Liu et al. 2023). The loss is the objective's regression target averaged over the real,
unpadded steps of each chunk (:func:`masked_mse`). How a chunk is sampled by default is part of the model
(``sample_steps`` network calls of ``solver``), so a checkpoint carries the settings it was made for.

The network is injected by name too: the 1-D temporal U-Net with FiLM (:class:`~kpflow.policies.kcfm.networks.unet1d.ConditionalUnet1D`,
any widths up to DP's (256, 512, 1024)) or a small transformer
(:class:`~kpflow.policies.kcfm.networks.transformer1d.ConditionalTransformer1D`). The condition ``c`` is the ``n_obs`` frames of
keypoints, each standardised with the same per-coordinate statistics and flattened. With a ``goal_frame`` (planar
tasks: which keypoints are the goal's, and their ``template``, where they lie in the goal's own body frame; the task's
config gives it, e.g. :func:`kpflow.tasks.pusht.geometry.goal_frame`) every frame is first expressed in the frame of
the current goal, the rigid fit ``(R, p) = argmin_{R in SO(2), p} sum_i ||R k_i + p - g_i||^2`` of the template
``k_i`` onto the observed goal keypoints ``g_i`` (:func:`~kpflow.geometry.alignment.fit_affine`, ``"rigid"``): then the
policy is equivariant to rotating and translating the whole scene by construction. With an ``origin`` (any dimension:
the index of the robot's keypoint, e.g. a gripper's grip site) every frame is instead translated by minus that keypoint
of the current frame, ``k_i - k_o``, and the actions' positions (their first ``D`` values) are predicted as offsets
from it: the policy is invariant to translating the whole scene by construction. Actions are expressed in the
*action frame* of the current observation: the goal's (``goal_frame``), moved to the agent (``relative=True``: a
chunk is then the agent's offsets from where it stands), and scaled to [-1, 1] per dimension by their training
min/max over every step of the chunks (as in Diffusion Policy). All statistics live in buffers and an exponential
moving average of the weights is kept beside them, so a checkpoint is all a deployment needs:
``load_checkpoint(KCFM, path).sample(keypoints)``. Hyper-parameters are plain names, numbers and lists of them:
loading a checkpoint never builds anything a file names.
"""

from __future__ import annotations

import copy
import math
from typing import Sequence

import lightning
import numpy as np
import torch

from kpflow.geometry.alignment import fit_affine
from kpflow.policies.checks import INPUT_MARGIN
from kpflow.policies.kcfm.networks.transformer1d import ConditionalTransformer1D
from kpflow.policies.kcfm.networks.unet1d import ConditionalUnet1D
from kpflow.policies.kcfm.objectives import build_objective
from kpflow.policies.settings import CHECKPOINT_KEY, PolicySettings

from .frames import check_frames, from_frame, to_frame
from .losses import fill_padding, masked_mse
from .sampling import check_sampler

NETWORKS = ("unet", "transformer")
LR_SCHEDULES = ("cosine", "constant")
_MIN_STD = 1e-3  # px: a keypoint coordinate with a smaller spread (e.g. a fixed goal) is centred but not scaled
_MIN_HALF_RANGE = 1e-6  # an action dimension with a smaller range is centred but not scaled
_BOX_STDS = 3.0  # the box of one keypoint coordinate: its training mean +- this many standard deviations


# ------------------------------------------------------------------------------------------------- losses


def _float64(x) -> torch.Tensor:
    """An array-like or tensor (any device) as a float64 CPU tensor."""
    if isinstance(x, torch.Tensor):
        return x.detach().to("cpu", torch.float64)
    return torch.as_tensor(np.asarray(x, dtype=np.float64))


# ------------------------------------------------------------------------------------------------ policy


class KCFM(lightning.LightningModule):
    """Keypoint-conditioned generative policy for action chunks (see the module docstring).

    Args:
        n_keypoints: keypoints per observation (the task's: 25 for Push-T).
        horizon: chunk length ``H`` (must match the datamodule's).
        n_obs: observation frames it conditions on, oldest first and ending at the current one (must match the
            datamodule's; Diffusion Policy uses 2).
        keypoint_dim: coordinates per keypoint (2 for Push-T, 3 for the robosuite tasks).
        action_dim: size of one action (2: an absolute agent target in px).
        goal_frame: express keypoints and actions in the frame of the goal (:meth:`goal_pose`):
            ``{"keypoints": [...], "template": [[x, y], ...]}``, the goal's keypoint indices and where each lies in the
            goal's body frame (:func:`check_goal_frame`; Push-T's: :func:`kpflow.tasks.pusht.geometry.goal_frame`);
            predictions are mapped back to the world. Planar: needs 2-D keypoints and actions. None: the world frame.
        relative: predict actions as offsets from the agent, the last keypoint (in the goal's axes with
            ``goal_frame``). Needs 2-D actions.
        origin: the index of the keypoint (negative: from the end) that keypoints and the actions' positions (their
            first ``keypoint_dim`` values) are taken relative to, in any dimension (module docstring). None: off.
            Not with ``goal_frame`` or ``relative``.
        objective: ``"icfm"``, ``"otcfm"``, ``"ddpm"``, ``"meanflow"`` or ``"reflow"``
            (:data:`~kpflow.policies.kcfm.objectives.OBJECTIVES`), built with ``objective_options`` (e.g.
            ``{"train_steps": 100}`` for ``"ddpm"``; ``{"teacher": "path/to/teacher.ckpt"}`` for ``"reflow"``, whose
            teacher is read when training starts, :meth:`attach_teacher`).
        sample_steps: network calls per chunk when :meth:`sample` is not told (1..``MAX_STEPS``).
        solver: the objective's sampler when :meth:`sample` is not told (``"euler"``, ``"midpoint"``, ``"heun"`` for
            flows, ``"ddim"`` for ``"ddpm"``; :mod:`~kpflow.policies.kcfm.objectives.solvers`); None: the objective's first.
        network: ``"unet"`` or ``"transformer"``.
        down_dims, kernel_size, n_groups: the :class:`~kpflow.policies.kcfm.networks.unet1d.ConditionalUnet1D`.
        d_model, n_layers, n_heads: the :class:`~kpflow.policies.kcfm.networks.transformer1d.ConditionalTransformer1D`.
        time_dim: size of the network's time embedding.
        lr, weight_decay: AdamW.
        lr_schedule: ``"cosine"`` (to 0 over the trainer's ``estimated_stepping_batches``) or ``"constant"``.
        warmup_steps: linear LR warm-up before the schedule.
        ema_decay: decay of the exponential moving average of the weights; the decay used at optimizer step
            ``n`` is ``min(ema_decay, (1 + n) / (10 + n))`` so the average forgets its random start quickly.
    """

    def __init__(
        self,
        n_keypoints: int,
        horizon: int = 20,
        n_obs: int = 1,
        action_dim: int = 2,
        keypoint_dim: int = 2,
        goal_frame: dict | None = None,
        relative: bool = False,
        origin: int | None = None,
        objective: str = "icfm",
        objective_options: dict | None = None,
        sample_steps: int = 10,
        solver: str | None = None,
        network: str = "unet",
        down_dims: Sequence[int] = (32, 64),
        kernel_size: int = 5,
        n_groups: int = 8,
        d_model: int = 128,
        n_layers: int = 4,
        n_heads: int = 4,
        time_dim: int = 64,
        lr: float = 1e-3,
        weight_decay: float = 1e-6,
        lr_schedule: str = "cosine",
        warmup_steps: int = 0,
        ema_decay: float = 0.999,
    ) -> None:
        super().__init__()
        if horizon < 1 or n_obs < 1 or n_keypoints < 1 or action_dim < 1 or keypoint_dim < 1:
            raise ValueError(
                f"need horizon, n_obs, n_keypoints, action_dim, keypoint_dim >= 1; got {horizon}, {n_obs}, {n_keypoints}, {action_dim}, {keypoint_dim}"
            )
        check_frames(goal_frame, relative, origin, n_keypoints, keypoint_dim, action_dim)
        if network not in NETWORKS:
            raise ValueError(f"network must be one of {NETWORKS}; got {network!r}")
        if lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}; got {lr_schedule!r}")
        if not 0.0 <= ema_decay < 1.0:
            raise ValueError(f"ema_decay must be in [0, 1); got {ema_decay}")
        if warmup_steps < 0:
            raise ValueError(f"warmup_steps must be >= 0; got {warmup_steps}")
        self.objective = build_objective(objective, **(objective_options or {}))  # validates the name and options
        check_sampler(self.objective, sample_steps, solver)
        self.save_hyperparameters()
        cond_dim, times = (
            keypoint_dim * n_keypoints * n_obs,
            dict(n_times=self.objective.n_times, time_scale=self.objective.time_scale),
        )
        if network == "unet":
            self.net = ConditionalUnet1D(
                action_dim, cond_dim, tuple(down_dims), kernel_size, n_groups, time_dim, **times
            )
        else:
            self.net = ConditionalTransformer1D(
                action_dim, cond_dim, horizon, d_model, n_layers, n_heads, time_dim, **times
            )
        self.ema_net = copy.deepcopy(self.net).requires_grad_(False)
        self.register_buffer("kp_mean", torch.zeros(keypoint_dim * n_keypoints))
        self.register_buffer("kp_std", torch.ones(keypoint_dim * n_keypoints))
        self.register_buffer("action_center", torch.zeros(action_dim))
        self.register_buffer("action_scale", torch.ones(action_dim))
        self.register_buffer("stats_set", torch.tensor(False))
        self.settings = (
            PolicySettings()
        )  # how it acts once released (kpflow/policies/settings.py): read from its checkpoint
        self.policy_config = None  # what it is and how it acts (kpflow/policies/config.py): read from its checkpoint

    # ------------------------------------------------------------------------------------ normalisation

    def set_normalisation(self, keypoints, chunks, mask=None) -> None:
        """Fit the statistics to world-frame ``keypoints [N, K, D]`` and their action ``chunks [N, H, A]`` (or single
        actions ``[N, A]``), counting only the steps where ``mask [N, H]`` is true (all when None).

        Keypoints (in the goal frame if ``goal_frame``) are standardised per coordinate; a coordinate with a spread
        under 1e-3 px is only centred. Actions (in their row's action frame, see :meth:`action_frame`) are mapped
        to [-1, 1] per dimension by their min/max.
        """
        kp, act = _float64(keypoints), _float64(chunks)
        k, a, d = self.hparams.n_keypoints, self.hparams.action_dim, self.hparams.keypoint_dim
        if act.ndim == 2:
            act = act[:, None]
        if kp.ndim != 3 or kp.shape[1:] != (k, d) or act.ndim != 3 or act.shape[::2] != (len(kp), a) or len(kp) == 0:
            raise ValueError(
                f"need keypoints [N, {k}, {d}] and actions [N, {a}] or [N, H, {a}] with N >= 1; "
                f"got {tuple(kp.shape)} and {tuple(_float64(chunks).shape)}"
            )
        mask = torch.ones(act.shape[:2], dtype=torch.bool) if mask is None else torch.as_tensor(np.asarray(mask)).bool()
        if mask.shape != act.shape[:2] or not mask.any():
            raise ValueError(f"mask must be [N, H] = {tuple(act.shape[:2])} with a true entry; got {tuple(mask.shape)}")
        for name, x in (("keypoints", kp), ("actions", act)):
            bad = ~torch.isfinite(x).reshape(len(x), -1).all(-1)
            if bad.any():
                raise ValueError(
                    f"training {name} contain NaN or inf (rows {torch.nonzero(bad).flatten()[:10].tolist()})"
                )
        frame = self.action_frame(kp)
        if frame is not None:
            act = to_frame(act, *frame)
        kp = self._stats_frame(kp[:, None])[:, 0]
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
        """Fit the normalisation to ``trainer.datamodule.train_set`` (once; a resumed run keeps the checkpoint's), or
        take the teacher's with an objective that distils one (:meth:`attach_teacher`)."""
        if stage == "fit" and hasattr(self.objective, "attach"):
            self.attach_teacher()
        if stage != "fit" or self.trainer is None or bool(self.stats_set):
            return
        ds = getattr(self.trainer.datamodule, "train_set", None)
        if ds is None:
            raise ValueError(
                "KCFM takes its normalisation from trainer.datamodule.train_set: fit it with datamodule=ChunkDataModule(...) "
                "or call set_normalisation() first"
            )
        if getattr(ds, "horizon", self.hparams.horizon) != self.hparams.horizon:
            raise ValueError(
                f"the data's chunk horizon {ds.horizon} differs from the model's horizon={self.hparams.horizon}"
            )
        if getattr(ds, "n_obs", 1) != self.hparams.n_obs:
            raise ValueError(
                f"the data's observation history n_obs={getattr(ds, 'n_obs', 1)} differs from the model's n_obs={self.hparams.n_obs}"
            )
        obs, chunks, mask = ds.arrays()  # one row per step of the training episodes only
        self.set_normalisation(obs, chunks, mask)

    def attach_teacher(self) -> None:
        """Read the teacher K-CFM of a distilling objective (``objective_options["teacher"]``, a checkpoint path) and
        hand the objective its sampler (its EMA network, ``teacher_steps`` calls of ``teacher_solver``).

        The student takes the teacher's normalisation (so that a condition and a normalised chunk mean the same to
        both) and, with ``initialise`` (the default) and the same network, starts from the teacher's weights; a
        resumed run's checkpoint then overwrites those. The teacher must see the same keypoints and predict the same
        actions: its layout, horizon, observation history and frames must equal the student's.

        Raises:
            ValueError: a teacher whose layout or frames differ, or whose network differs when ``initialise``.
        """
        from kpflow.utils.checkpoint import load_checkpoint

        teacher = load_checkpoint(KCFM, self.objective.teacher, map_location=self.device).eval()
        same = ("n_keypoints", "keypoint_dim", "action_dim", "horizon", "n_obs", "goal_frame", "relative", "origin")
        differ = [k for k in same if teacher.hparams.get(k) != self.hparams.get(k)]
        if differ:
            raise ValueError(
                f"the teacher {self.objective.teacher} differs from this K-CFM in {differ}: "
                + ", ".join(f"{k} {teacher.hparams.get(k)!r} against {self.hparams.get(k)!r}" for k in differ)
            )
        with torch.no_grad():
            for name in ("kp_mean", "kp_std", "action_center", "action_scale", "stats_set"):
                getattr(self, name).copy_(getattr(teacher, name))
            if self.objective.initialise:
                try:
                    self.net.load_state_dict(teacher.ema_net.state_dict())
                    self.ema_net.load_state_dict(teacher.ema_net.state_dict())
                except RuntimeError as e:
                    raise ValueError(
                        f"initialise=True starts the student from the teacher's weights, but their networks differ ({e})"
                    ) from None
        steps, solver = self.objective.teacher_steps, self.objective.teacher_solver
        check_sampler(teacher.objective, steps, solver)

        def teacher_sample(noise: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
            teacher.to(noise.device)  # it follows the student (the trainer moves the student after setup)
            return teacher.objective.sample(lambda x, t: teacher.ema_net(x, t, c), noise, steps, solver)

        self.objective.attach(teacher_sample)

    def _stats_frame(
        self, history: torch.Tensor, pose: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> torch.Tensor:
        """World keypoint frames ``[B, n_obs, K, D]`` (float64) in the frame the keypoint statistics are in: every
        frame in the current (last) frame's goal frame if ``goal_frame`` (``pose``: that frame's :meth:`goal_pose`,
        when the caller has it already), relative to the current frame's ``origin`` keypoint if one is set, else as
        they are."""
        kp = history.to(torch.float64)
        if self.hparams.goal_frame is not None:
            kp = to_frame(kp.flatten(1, 2), *(self.goal_pose(kp[:, -1]) if pose is None else pose)).reshape(kp.shape)
        elif self.hparams.get("origin") is not None:
            kp = kp - kp[:, -1, self.hparams.origin][:, None, None]
        return kp

    def goal_pose(self, keypoints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The goal's frame ``(R [B, 2, 2], p [B, 2])`` in keypoint frames ``[B, K, 2]``: the rigid (Kabsch) fit
        ``min_{R in SO(2), p} sum_i ||R k_i + p - g_i||^2`` of the ``goal_frame`` template ``k_i`` onto the goal's
        keypoints ``g_i`` (:func:`~kpflow.geometry.alignment.fit_affine`). Exact for a goal at any pose (Push-T: ``p, theta``
        are the goal T's ``x, y, theta``)."""
        spec = self.hparams.goal_frame
        goal = keypoints[:, spec["keypoints"]]
        template = torch.as_tensor(spec["template"], dtype=goal.dtype, device=goal.device)
        return fit_affine(template.expand_as(goal), goal, "rigid")

    def _condition(self, history: torch.Tensor, stats_frame: torch.Tensor | None = None) -> torch.Tensor:
        """Condition ``c [B, n_obs D K]`` (float32) of world keypoint frames ``[B, n_obs, K, D]``: every frame in the
        statistics' frame (:meth:`_stats_frame`; ``stats_frame``: those frames, when the caller has them already),
        standardised, concatenated oldest first."""
        kp = self._stats_frame(history) if stats_frame is None else stats_frame
        b, n = kp.shape[:2]
        return ((kp.reshape(b, n, -1) - self.kp_mean.double()) / self.kp_std.double()).reshape(b, -1).float()

    def action_frame(
        self, keypoints: torch.Tensor, pose: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The rigid frame ``(R [B, 2, 2], p [B, 2])`` that actions are predicted in, for keypoints ``[B, K, 2]``.

        ``R`` is the goal's rotation with ``goal_frame`` (else the identity), ``p`` the agent (the last keypoint) with
        ``relative`` (else the goal's origin, or 0). With ``origin``: ``(I [B, D, D], the origin keypoint)``, applied
        to the actions' first ``D`` values. None when all are off: actions stay in world coordinates. ``pose``: the
        keypoints' :meth:`goal_pose`, when the caller has it already.
        """
        hp = self.hparams
        kp = keypoints.to(torch.float64)
        if hp.get("origin") is not None:
            d = hp.keypoint_dim
            return torch.eye(d, dtype=kp.dtype, device=kp.device).expand(len(kp), d, d), kp[:, hp.origin]
        if hp.goal_frame is None and not hp.relative:
            return None
        if hp.goal_frame is not None:
            rot, origin = self.goal_pose(kp) if pose is None else pose
        else:
            rot, origin = (
                torch.eye(2, dtype=kp.dtype, device=kp.device).expand(len(kp), 2, 2),
                torch.zeros_like(kp[:, 0]),
            )
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

    def _history(self, batch: dict) -> torch.Tensor:
        """The batch's keypoint frames ``[B, n_obs, K, D]``: ``batch["history"]``, or ``batch["obs"]`` as one frame."""
        if "history" in batch:
            return batch["history"]
        if self.hparams.n_obs != 1:
            raise ValueError(
                f"the model conditions on n_obs={self.hparams.n_obs} frames: the batch needs 'history' [B, n_obs, K, D]"
            )
        return batch["obs"][:, None]

    def loss(
        self, batch: dict, net: torch.nn.Module | None = None, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """The objective's masked regression loss on a :class:`~kpflow.data.chunks.ChunkDataset` batch.

        ``L = masked_mse(net(x_t, t, c[i]), target, mask[i])`` with ``(x_t, t, target, i)`` the objective's
        :class:`~kpflow.policies.kcfm.objectives.TrainingTarget` for ``x1``, the normalised chunks (padding filled by
        :func:`fill_padding`); noise from ``generator``. ``net`` defaults to the trained (non-EMA) network.
        """
        actions, mask = batch["actions"], batch["mask"]
        history = self._history(batch)
        k, h, a, n = self.hparams.n_keypoints, self.hparams.horizon, self.hparams.action_dim, self.hparams.n_obs
        d, b = self.hparams.keypoint_dim, len(actions)
        if history.shape != (b, n, k, d) or actions.shape != (b, h, a) or mask.shape != (b, h):
            raise ValueError(
                f"batch must hold history [B, {n}, {k}, {d}] (or obs [B, {k}, {d}] when n_obs=1), actions [B, {h}, {a}] and "
                f"mask [B, {h}]; got {tuple(history.shape)}, {tuple(actions.shape)}, {tuple(mask.shape)}"
            )
        history = history.to(torch.float64)
        pose = self.goal_pose(history[:, -1]) if self.hparams.goal_frame is not None else None
        c = self._condition(history, self._stats_frame(history, pose))
        x1 = self.normalise_actions(fill_padding(actions, mask.bool()), self.action_frame(history[:, -1], pose))
        net = self.net if net is None else net
        target = self.objective.training_target(x1, c, generator, net)
        i = target.index
        return masked_mse(net(target.x_t, target.t, c[i]), target.target, mask.bool()[i])

    def training_step(self, batch, batch_idx: int) -> torch.Tensor:
        loss = self.loss(batch)
        self.log("train/loss", loss, prog_bar=True, batch_size=len(batch["actions"]))
        return loss

    def validation_step(self, batch, batch_idx: int) -> None:
        # EMA weights, and noise fixed per batch so that the validation loss compares across epochs.
        generator = torch.Generator(device=self.device).manual_seed(batch_idx)
        self.log(
            "val/loss",
            self.loss(batch, net=self.ema_net, generator=generator),
            prog_bar=True,
            batch_size=len(batch["actions"]),
        )

    @torch.no_grad()
    def on_train_batch_end(self, outputs, batch, batch_idx: int) -> None:
        """EMA update ``theta_ema <- d theta_ema + (1 - d) theta`` with ``d = min(ema_decay, (1 + n) / (10 + n))``."""
        n = self.global_step
        decay = min(self.hparams.ema_decay, (1 + n) / (10 + n))
        for ema, p in zip(self.ema_net.parameters(), self.net.parameters()):
            ema.lerp_(p, 1.0 - decay)

    @staticmethod
    def complete_state_dict(state: dict) -> dict:
        """A state dict with the trained network's weights: a release that keeps the EMA network alone (what
        :meth:`sample` uses; ``kpflow-release ema_only=true``) starts the trained one as its copy."""
        if any(k.startswith("net.") for k in state) or not any(k.startswith("ema_net.") for k in state):
            return state
        return {**state, **{"net." + k[len("ema_net.") :]: v for k, v in state.items() if k.startswith("ema_net.")}}

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
        """Keypoints as a finite float64 tensor ``[B, n_obs, K, D]`` on the model's device.

        Accepted: ``[B, n_obs, K, D]``; one history ``[n_obs, K, D]``; and, when ``n_obs = 1``, one frame ``[K, D]``
        or a batch of frames ``[B, K, D]``.
        """
        if isinstance(keypoints, torch.Tensor):
            kp = keypoints
            if kp.is_complex() or kp.dtype == torch.bool:
                raise ValueError(f"keypoints must be real numbers; got dtype {kp.dtype}")
        else:
            try:
                kp = torch.as_tensor(np.asarray(keypoints, dtype=np.float64))
            except (TypeError, ValueError) as e:
                raise ValueError(f"keypoints must be an array of numbers ({e})") from e
        k, n, d, shape = self.hparams.n_keypoints, self.hparams.n_obs, self.hparams.keypoint_dim, tuple(kp.shape)
        if kp.ndim == 2 and n == 1:
            kp = kp[None, None]
        elif kp.ndim == 3:
            kp = kp[:, None] if n == 1 else kp[None]
        if kp.ndim != 4 or kp.shape[1:] != (n, k, d) or len(kp) == 0:
            single = f"[{k}, {d}], [B, {k}, {d}] or " if n == 1 else ""
            raise ValueError(
                f"keypoints must have shape {single}[{n}, {k}, {d}] or [B, {n}, {k}, {d}] (n_obs={n} frames) with B >= 1; got {shape}"
            )
        kp = kp.to(self.device, torch.float64)
        bad = ~torch.isfinite(kp).reshape(len(kp), -1).all(-1)
        if bad.any():
            raise ValueError(f"keypoints contain NaN or inf (batch items {torch.nonzero(bad).flatten()[:10].tolist()})")
        return kp

    def keypoint_box(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The box ``(lo [D], hi [D])`` (float64) of the training keypoints, in the frame of the statistics (the
        goal's with ``goal_frame``, else the world): per dimension, the least ``mean - 3 std`` and the largest
        ``mean + 3 std`` over every keypoint's statistics (the normalisation buffers; a checkpoint carries them)."""
        d = self.hparams.keypoint_dim
        mean, std = self.kp_mean.double().reshape(-1, d), self.kp_std.double().reshape(-1, d)
        return (mean - _BOX_STDS * std).min(0).values, (mean + _BOX_STDS * std).max(0).values

    def check_in_range(self, keypoints, input_margin: float | None = INPUT_MARGIN) -> torch.Tensor:
        """Keypoint frames checked by :meth:`_check_keypoints` (shape, finite) and refused when far outside the data
        the model was trained on; returned as ``[B, n_obs, K, D]`` float64.

        With ``(lo, hi)`` the :meth:`keypoint_box` and ``w = hi - lo``, every coordinate must lie in
        ``[lo - m w, hi + m w]`` (``m = input_margin``, per dimension): in the world and, with ``goal_frame``, in the
        goal's frame too (the statistics' frame; a goal-frame model's statistics say nothing of where the goal is, so
        its world coordinates are held to the same widened box). Nothing is checked when ``input_margin`` is None or
        the statistics were never set (an untrained model has no range).

        Raises:
            ValueError: naming the first keypoint outside, its coordinates, the accepted interval and the box.
        """
        kp = self._check_keypoints(keypoints)
        if input_margin is not None:
            self._check_range(kp, self._stats_frame(kp), input_margin)
        return kp

    def _check_range(self, kp: torch.Tensor, stats_frame: torch.Tensor, input_margin: float | None) -> None:
        """:meth:`check_in_range`'s test of checked keypoint frames ``kp`` and those frames in the statistics' frame."""
        if input_margin is None or not bool(self.stats_set):
            return
        lo, hi = self.keypoint_box()
        lo_ok, hi_ok = lo - input_margin * (hi - lo), hi + input_margin * (hi - lo)
        if self.hparams.get("origin") is not None:  # statistics relative to a keypoint say nothing of the world
            frames = [(f" relative to keypoint {self.hparams.origin}", stats_frame)]
        else:
            frames = [("", kp)] + (
                [(" in the goal's frame", stats_frame)] if self.hparams.goal_frame is not None else []
            )
        for where, x in frames:
            outside = ~((x >= lo_ok) & (x <= hi_ok))  # NaN (a frame that overflowed) counts as outside
            if outside.any():
                b, f, k, d = (int(i) for i in torch.nonzero(outside)[0])
                frame = f" of observation frame {f}" if self.hparams.n_obs > 1 else ""
                at = ", ".join(f"{v:.4g}" for v in kp[b, f, k].tolist())
                raise ValueError(
                    f"the observation is far outside the range this K-CFM was trained on: keypoint {k}{frame} at ({at}) has "
                    f"coordinate {d} = {float(x[b, f, k, d]):.4g}{where}, outside the accepted [{float(lo_ok[d]):.4g}, "
                    f"{float(hi_ok[d]):.4g}] (the training keypoints' box [{float(lo[d]):.4g}, {float(hi[d]):.4g}], mean +- "
                    f"{_BOX_STDS:g} std, widened by input_margin={input_margin:g} times its extent on each side); refusing to act on it"
                )

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Read the settings a released checkpoint carries (:class:`~kpflow.policies.settings.PolicySettings`) and
        check them against this model: ``steps`` and ``solver`` must suit its objective, ``execute`` its chunk length
        (``ValueError`` naming the setting; :func:`~kpflow.utils.checkpoint.load_checkpoint` adds the file); and the
        policy's whole config (:class:`~kpflow.policies.config.PolicyConfig`: its kind, transport and keypoint
        layout; a checkpoint without one: a bare K-CFM) into :attr:`policy_config`."""
        from kpflow.policies.config import PolicyConfig

        self.policy_config = PolicyConfig.of_checkpoint(checkpoint, "its policy_config")
        settings = self.policy_config.settings
        try:
            check_sampler(self.objective, settings.steps or 1, settings.solver)
        except ValueError as e:
            raise ValueError(f"its {CHECKPOINT_KEY} do not suit the model: {e}") from None
        if settings.execute is not None and settings.execute > int(self.hparams.horizon):
            raise ValueError(f"its {CHECKPOINT_KEY} do not suit the model: execute = {settings.execute} is beyond the model's chunk length "
                             f"(horizon {int(self.hparams.horizon)}); kpflow-release settings.execute=N with N <= {int(self.hparams.horizon)}")  # fmt: skip
        self.settings = settings

    def sampler(self, steps: int | None = None, solver: str | None = None) -> tuple[int, str]:
        """``(steps, solver)`` as :meth:`sample` uses them: the given ones, else the released settings' (:attr:`settings`),
        else the model's ``sample_steps`` and ``solver`` (checkpoints from before those: 10 calls of the objective's
        first solver)."""
        steps = steps if steps is not None else self.settings.steps or int(self.hparams.get("sample_steps", 10))
        solver = (
            solver
            if solver is not None
            else self.settings.solver or self.hparams.get("solver") or self.objective.solvers[0]
        )
        check_sampler(self.objective, steps, solver)
        return int(steps), solver

    @torch.no_grad()
    def sample(self, keypoints, steps: int | None = None, generator: torch.Generator | None = None, solver: str | None = None,
               net=None, input_margin: float | None = None) -> torch.Tensor:  # fmt: skip
        """Action chunks ``[B, H, A]`` (float32, world px) for keypoint frames (shapes: :meth:`_check_keypoints`).

        The objective's sampler ``solver`` (an ODE solver of the flow, DDIM for the diffusion) with ``steps`` calls of
        the EMA network (None: the model's own settings, :meth:`sampler`), from ``x ~ N(0, I)`` drawn with
        ``generator`` (on the generator's device). Deterministic given the generator's state. ``net``: what runs the
        EMA network, e.g. its :class:`~kpflow.policies.kcfm.traced.TracedNetwork` (None: the module itself).
        ``input_margin``: refuse keypoints far outside the training data, as :meth:`check_in_range` does (None: not
        checked). The goal's frame is fitted once and serves the check, the condition and the actions' frame.

        Raises:
            ValueError: ``steps`` not an integer in ``1..MAX_STEPS``; a solver the objective lacks; keypoints of the
                wrong shape, not finite or (with ``input_margin``) out of range.
        """
        steps, solver = self.sampler(steps, solver)
        kp = self._check_keypoints(keypoints)
        pose = self.goal_pose(kp[:, -1]) if self.hparams.goal_frame is not None else None
        stats_frame = self._stats_frame(kp, pose)
        self._check_range(kp, stats_frame, input_margin)
        c, frame = self._condition(kp, stats_frame), self.action_frame(kp[:, -1], pose)
        noise = self._randn((len(kp), self.hparams.horizon, self.hparams.action_dim), generator)
        net = self.ema_net if net is None else net
        x = self.objective.sample(lambda x, t: net(x, t, c), noise, steps, solver)
        return self.denormalise_actions(x, frame)

    def forward(
        self, keypoints, steps: int | None = None, generator: torch.Generator | None = None, solver: str | None = None
    ) -> torch.Tensor:
        """Same as :meth:`sample`."""
        return self.sample(keypoints, steps, generator, solver)
