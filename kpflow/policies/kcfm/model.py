"""K-CFM: keypoint-conditioned generative policy of action chunks.

A policy ``pi(a_{t:t+H} | k_{t-n+1..t})`` that generates a chunk of ``H`` actions (e.g. absolute agent targets) from
the last ``n_obs`` observations of a task's ``K`` keypoints ``k`` (Push-T: 25, block T, goal T and agent,
:mod:`kpflow.tasks.pusht.geometry`) by denoising Gaussian noise with a conditional network.

It is shaped as LeRobot shapes a policy: one config (:class:`~kpflow.policies.kcfm.config.KCFMConfig`, what the
constructor takes and a checkpoint's hyper-parameters hold), a processor apart from the model
(:class:`~kpflow.policies.kcfm.processor.KeypointProcessor`: frames, normalisation, range check), fitted from the
statistics the data module passes in (:meth:`KCFM.fit_processor` with
:meth:`~kpflow.data.chunks.ChunkDataModule.training_chunks`; ``kpflow-train`` does it before training), and the
network and the objective each a registered name plus options:

- The generative objective (:mod:`kpflow.policies.kcfm.objectives`): ``"icfm"`` (conditional flow matching, the
  straight path with ``sigma = 0``: Lipman et al. 2023 eqs. 20-23, the default), ``"otcfm"`` (with minibatch
  optimal-transport couplings, Tong et al. 2024), ``"ddpm"`` (DDPM training and DDIM sampling as Diffusion Policy does
  it: with the same network, data and budget, the DP-equivalent baseline), ``"meanflow"`` (average velocities, one
  step from noise to data, Geng et al. 2025) or ``"reflow"`` (distillation of a trained K-CFM, the *teacher*, into few
  steps: Liu et al. 2023). The loss is the objective's regression target averaged over the real, unpadded steps of
  each chunk (:func:`masked_mse`). How a chunk is sampled by default is part of the model (``sampler.steps`` network
  calls of ``sampler.solver``), so a checkpoint carries the settings it was made for.
- The network (:mod:`kpflow.policies.kcfm.networks`): the 1-D temporal U-Net with FiLM (``"unet"``, any widths up to
  DP's (256, 512, 1024)) or a small transformer (``"transformer"``). Its condition ``c`` is the ``n_obs`` frames of
  keypoints in the processor's frame, standardised and flattened; it predicts actions in the processor's action
  frame, scaled to [-1, 1].

The statistics live in the processor's buffers and an exponential moving average of the weights is kept beside the
trained network, so a checkpoint is all a deployment needs: ``load_checkpoint(KCFM, path).sample(keypoints)``.
Hyper-parameters are plain names, numbers, lists and dicts of them: loading a checkpoint never builds anything a file
names.
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict

import lightning
import torch

from kpflow.policies.checks import INPUT_MARGIN
from kpflow.policies.kcfm.networks import NetworkDims, build_network
from kpflow.policies.kcfm.objectives import build_objective
from kpflow.policies.settings import CHECKPOINT_KEY, PolicySettings

from .config import KCFMConfig, migrate
from .losses import fill_padding, masked_mse
from .processor import STATISTICS, KeypointProcessor
from .sampling import check_sampler


class KCFM(lightning.LightningModule):
    """Keypoint-conditioned generative policy for action chunks (see the module docstring).

    Args:
        n_keypoints: keypoints per observation (the task's: 25 for Push-T).
        horizon: chunk length ``H`` (must match the datamodule's).
        n_obs: observation frames it conditions on, oldest first and ending at the current one (must match the
            datamodule's; Diffusion Policy uses 2).
        action_dim: size of one action (2: an absolute agent target in px).
        keypoint_dim: coordinates per keypoint (2 for Push-T, 3 for the robosuite tasks).
        processor: the frames, ``{goal_frame, relative, origin}``
            (:class:`~kpflow.policies.kcfm.config.ProcessorConfig`, :class:`~kpflow.policies.kcfm.processor.KeypointProcessor`).
        network: ``{name: "unet" | "transformer", **options}`` (:data:`~kpflow.policies.kcfm.networks.NETWORKS`; e.g.
            ``{"name": "unet", "down_dims": [64, 128]}``).
        objective: ``{name: "icfm" | "otcfm" | "ddpm" | "meanflow" | "reflow", **options}``
            (:data:`~kpflow.policies.kcfm.objectives.OBJECTIVES`; e.g. ``{"name": "ddpm", "train_steps": 100}``,
            ``{"name": "reflow", "teacher": "path/to/teacher.ckpt"}``, whose teacher is read when training starts,
            :meth:`attach_teacher`).
        sampler: ``{steps, solver}``, how :meth:`sample` samples when not told (1..``MAX_STEPS`` network calls of
            ``"euler"``, ``"midpoint"``, ``"heun"`` for flows, ``"ddim"`` for ``"ddpm"``; solver None: the
            objective's first).
        optim: ``{lr, weight_decay, lr_schedule, warmup_steps, ema_decay}`` (:class:`~kpflow.policies.kcfm.config.OptimConfig`):
            AdamW; ``"cosine"`` (to 0 over the trainer's ``estimated_stepping_batches``) or ``"constant"``; linear
            warm-up; the EMA's decay, used at optimizer step ``n`` as ``min(ema_decay, (1 + n) / (10 + n))``.
        Each group may be given as its dataclass too; a name alone stands for ``{name: NAME}``.
    """

    def __init__(self, n_keypoints: int, horizon: int = 20, n_obs: int = 1, action_dim: int = 2, keypoint_dim: int = 2,
                 processor=None, network=None, objective=None, sampler=None, optim=None) -> None:  # fmt: skip
        super().__init__()
        cfg = KCFMConfig.of(n_keypoints, horizon, n_obs, action_dim, keypoint_dim, processor, network, objective,
                            sampler, optim)  # fmt: skip
        self.config = cfg
        self.processor = KeypointProcessor(cfg.n_keypoints, cfg.keypoint_dim, cfg.action_dim, cfg.n_obs,
                                           **asdict(cfg.processor))  # fmt: skip
        self.objective = build_objective(cfg.objective.name, **cfg.objective.options)  # validates name and options
        check_sampler(self.objective, cfg.sampler.steps, cfg.sampler.solver)
        self.save_hyperparameters(cfg.hparams())
        dims = NetworkDims(cfg.action_dim, cfg.keypoint_dim * cfg.n_keypoints * cfg.n_obs, cfg.horizon,
                           self.objective.n_times, self.objective.time_scale)  # fmt: skip
        self.net = build_network(cfg.network.name, dims, **cfg.network.options)
        self.ema_net = copy.deepcopy(self.net).requires_grad_(False)
        self.settings = (
            PolicySettings()
        )  # how it acts once released (kpflow/policies/settings.py): read from its checkpoint
        self.policy_config = None  # what it is and how it acts (kpflow/policies/config.py): read from its checkpoint

    #: moves a checkpoint's hyper-parameters of an older layout into the config's groups (kpflow.utils.checkpoint)
    migrate_hparams = staticmethod(migrate)

    # ------------------------------------------------------------------------------------ normalisation

    def fit_processor(self, data) -> None:
        """Fit the processor's statistics to the training data the data module passes in
        (:class:`~kpflow.data.chunks.TrainingChunks`: world keypoints, action chunks and their masks, one row per step
        of the training episodes), after checking that its chunks and histories are this model's.

        Raises:
            ValueError: the data's horizon or n_obs differ from the model's; data the processor refuses.
        """
        cfg = self.config
        if data.horizon != cfg.horizon:
            raise ValueError(f"the data's chunk horizon {data.horizon} differs from the model's horizon={cfg.horizon}")
        if data.n_obs != cfg.n_obs:
            raise ValueError(
                f"the data's observation history n_obs={data.n_obs} differs from the model's n_obs={cfg.n_obs}"
            )
        self.processor.fit(data.keypoints, data.chunks, data.mask)

    def setup(self, stage: str) -> None:
        """Take the teacher's statistics and weights with an objective that distils one (:meth:`attach_teacher`)."""
        if stage == "fit" and hasattr(self.objective, "attach"):
            self.attach_teacher()

    def on_fit_start(self) -> None:
        """Refuse to train with a processor never fitted (:meth:`fit_processor`; a resumed run has restored its own)."""
        if not self.processor.fitted:
            raise ValueError(
                "the K-CFM's processor was never fitted: call model.fit_processor(datamodule.training_chunks()) "
                "before trainer.fit (kpflow-train does), so that its statistics are the training data's"
            )

    def attach_teacher(self) -> None:
        """Read the teacher K-CFM of a distilling objective (``objective.teacher``, a checkpoint path) and
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
        same = ("n_keypoints", "keypoint_dim", "action_dim", "horizon", "n_obs", "processor")
        differ = [k for k in same if getattr(teacher.config, k) != getattr(self.config, k)]
        if differ:
            raise ValueError(
                f"the teacher {self.objective.teacher} differs from this K-CFM in {differ}: "
                + ", ".join(f"{k} {getattr(teacher.config, k)!r} against {getattr(self.config, k)!r}" for k in differ)
            )
        with torch.no_grad():
            self.processor.load_state_dict(teacher.processor.state_dict())
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

    # ----------------------------------------------------------------------------------------- training

    def _randn(self, shape, generator: torch.Generator | None) -> torch.Tensor:
        device = generator.device if generator is not None else self.device
        return torch.randn(shape, generator=generator, device=device).to(self.device)

    def _history(self, batch: dict) -> torch.Tensor:
        """The batch's keypoint frames ``[B, n_obs, K, D]``: ``batch["history"]``, or ``batch["obs"]`` as one frame."""
        if "history" in batch:
            return batch["history"]
        if self.config.n_obs != 1:
            raise ValueError(
                f"the model conditions on n_obs={self.config.n_obs} frames: the batch needs 'history' [B, n_obs, K, D]"
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
        cfg, pro = self.config, self.processor
        k, h, a, n, d, b = cfg.n_keypoints, cfg.horizon, cfg.action_dim, cfg.n_obs, cfg.keypoint_dim, len(actions)
        if history.shape != (b, n, k, d) or actions.shape != (b, h, a) or mask.shape != (b, h):
            raise ValueError(
                f"batch must hold history [B, {n}, {k}, {d}] (or obs [B, {k}, {d}] when n_obs=1), actions [B, {h}, {a}] and "
                f"mask [B, {h}]; got {tuple(history.shape)}, {tuple(actions.shape)}, {tuple(mask.shape)}"
            )
        history = history.to(torch.float64)
        pose = pro.pose(history)
        c = pro.condition(pro.stats_frame(history, pose))
        x1 = pro.normalise_actions(fill_padding(actions, mask.bool()), pro.action_frame(history[:, -1], pose))
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
        decay = min(self.config.optim.ema_decay, (1 + n) / (10 + n))
        for ema, p in zip(self.ema_net.parameters(), self.net.parameters()):
            ema.lerp_(p, 1.0 - decay)

    @staticmethod
    def complete_state_dict(state: dict) -> dict:
        """A checkpoint's state dict in this model's names: the processor's statistics of an older file (saved at the
        top, ``kp_mean``...) moved under ``processor.``, and a release that keeps the EMA network alone (what
        :meth:`sample` uses; ``kpflow-release ema_only=true``) given the trained network as its copy."""
        state = {("processor." + k if k in STATISTICS else k): v for k, v in state.items()}
        if any(k.startswith("net.") for k in state) or not any(k.startswith("ema_net.") for k in state):
            return state
        return {**state, **{"net." + k[len("ema_net.") :]: v for k, v in state.items() if k.startswith("ema_net.")}}

    def configure_optimizers(self):
        hp = self.config.optim
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

    def check_in_range(self, keypoints, input_margin: float | None = INPUT_MARGIN) -> torch.Tensor:
        """Keypoint frames checked for shape and finiteness and refused when far outside the data the model was
        trained on (:meth:`~kpflow.policies.kcfm.processor.KeypointProcessor.check_range`: the training keypoints'
        box widened by ``input_margin`` times its extent; None: not checked); returned as ``[B, n_obs, K, D]`` float64.

        Raises:
            ValueError: keypoints of the wrong shape or not finite; naming the first keypoint outside, its
                coordinates, the accepted interval and the box.
        """
        kp = self.processor.check_keypoints(keypoints, self.device)
        self.processor.check_range(kp, self.processor.stats_frame(kp), input_margin)
        return kp

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Bring an older checkpoint's weights to this model's names (:meth:`complete_state_dict`, also when a run
        resumes from it); read the settings a released checkpoint carries (:class:`~kpflow.policies.settings.PolicySettings`) and
        check them against this model: ``steps`` and ``solver`` must suit its objective, ``execute`` its chunk length
        (``ValueError`` naming the setting; :func:`~kpflow.utils.checkpoint.load_checkpoint` adds the file); and the
        policy's whole config (:class:`~kpflow.policies.config.PolicyConfig`: its kind, transport and keypoint
        layout; a checkpoint without one: a bare K-CFM) into :attr:`policy_config`."""
        from kpflow.policies.config import PolicyConfig

        checkpoint["state_dict"] = self.complete_state_dict(checkpoint["state_dict"])
        self.policy_config = PolicyConfig.of_checkpoint(checkpoint, "its policy_config")
        settings = self.policy_config.settings
        try:
            check_sampler(self.objective, settings.steps or 1, settings.solver)
        except ValueError as e:
            raise ValueError(f"its {CHECKPOINT_KEY} do not suit the model: {e}") from None
        if settings.execute is not None and settings.execute > self.config.horizon:
            raise ValueError(f"its {CHECKPOINT_KEY} do not suit the model: execute = {settings.execute} is beyond the model's chunk length "
                             f"(horizon {self.config.horizon}); kpflow-release settings.execute=N with N <= {self.config.horizon}")  # fmt: skip
        self.settings = settings

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """Write the policy's config (:attr:`policy_config`: its kind and the task's keypoint layout, set by
        ``kpflow-train task=...`` or read from the checkpoint it was loaded from) into every checkpoint it saves."""
        from kpflow.policies.config import CHECKPOINT_KEY as CONFIG_KEY

        if self.policy_config is not None:
            checkpoint[CONFIG_KEY] = self.policy_config.record()
            if self.policy_config.settings.record():
                checkpoint[CHECKPOINT_KEY] = self.policy_config.settings.record()

    def sampler(self, steps: int | None = None, solver: str | None = None) -> tuple[int, str]:
        """``(steps, solver)`` as :meth:`sample` uses them: the given ones, else the released settings' (:attr:`settings`),
        else the model's ``sampler`` (its solver None: the objective's first)."""
        steps = steps if steps is not None else self.settings.steps or self.config.sampler.steps
        solver = (
            solver
            if solver is not None
            else self.settings.solver or self.config.sampler.solver or self.objective.solvers[0]
        )
        check_sampler(self.objective, steps, solver)
        return int(steps), solver

    @torch.no_grad()
    def sample(self, keypoints, steps: int | None = None, generator: torch.Generator | None = None, solver: str | None = None,
               net=None, input_margin: float | None = None) -> torch.Tensor:  # fmt: skip
        """Action chunks ``[B, H, A]`` (float32, world px) for keypoint frames (shapes: :meth:`~kpflow.policies.kcfm.processor.KeypointProcessor.check_keypoints`).

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
        pro = self.processor
        kp = pro.check_keypoints(keypoints, self.device)
        pose = pro.pose(kp)
        stats_frame = pro.stats_frame(kp, pose)
        pro.check_range(kp, stats_frame, input_margin)
        c, frame = pro.condition(stats_frame), pro.action_frame(kp[:, -1], pose)
        noise = self._randn((len(kp), self.config.horizon, self.config.action_dim), generator)
        net = self.ema_net if net is None else net
        x = self.objective.sample(lambda x, t: net(x, t, c), noise, steps, solver)
        return pro.denormalise_actions(x, frame)

    def forward(
        self, keypoints, steps: int | None = None, generator: torch.Generator | None = None, solver: str | None = None
    ) -> torch.Tensor:
        """Same as :meth:`sample`."""
        return self.sample(keypoints, steps, generator, solver)
