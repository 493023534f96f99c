"""The K-CFM's processor: what stands between world keypoints and actions and the network (LeRobot's split of
processor and model). It owns the frames, the normalisation statistics and the range check; the network sees only
standardised conditions and actions in [-1, 1].

- Frames (:mod:`.frames`): with a ``goal_frame`` (planar tasks) every keypoint frame is expressed in the frame of the
  current goal, the rigid fit ``(R, p) = argmin_{R in SO(2), p} sum_i ||R k_i + p - g_i||^2`` of the goal's template
  ``k_i`` onto its observed keypoints ``g_i``; with an ``origin`` (any dimension) every frame is translated by minus
  that keypoint of the current frame, ``k_i - k_o``. Actions are predicted in the *action frame* of the current
  observation: the goal's (``goal_frame``), moved to the agent (``relative``), or at the origin keypoint (``origin``).
- Normalisation, fitted once to the training data (:meth:`KeypointProcessor.fit`, from the
  :class:`~kpflow.data.chunks.TrainingChunks` the data module hands over): keypoints standardised per coordinate,
  ``(k - mu) / sigma`` (a coordinate with ``sigma < 1e-3`` only centred); actions mapped to [-1, 1] per dimension by
  their min/max over every real step of the chunks, ``(a - (hi + lo) / 2) / ((hi - lo) / 2)`` (as in Diffusion
  Policy). A dimension that never changes in the data (a gripper always open) gets scale 0: the network sees 0 there
  and the policy returns the constant exactly, never the network's residual noise around it. The statistics are
  buffers, so a checkpoint carries them.
- The range check: the box of the training keypoints, per dimension the least ``mu - 3 sigma`` and the largest
  ``mu + 3 sigma``; an observation farther outside it than ``input_margin`` times its extent is refused by name.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from kpflow.geometry.alignment import fit_affine

from .frames import check_frames, from_frame, to_frame

_MIN_STD = 1e-3  # a keypoint coordinate with a smaller spread (e.g. a fixed goal) is centred but not scaled
_MIN_HALF_RANGE = 1e-6  # an action dimension with a smaller half range is a constant: scale 0, returned as its centre
_BOX_STDS = 3.0  # the box of one keypoint coordinate: its training mean +- this many standard deviations
#: the processor's buffers (the model's state dict holds them as ``processor.<name>``)
STATISTICS = ("kp_mean", "kp_std", "action_center", "action_scale", "stats_set")

Frame = tuple[torch.Tensor, torch.Tensor]


def _float64(x) -> torch.Tensor:
    """An array-like or tensor (any device) as a float64 CPU tensor."""
    if isinstance(x, torch.Tensor):
        return x.detach().to("cpu", torch.float64)
    return torch.as_tensor(np.asarray(x, dtype=np.float64))


class KeypointProcessor(nn.Module):
    """Frames, normalisation and range check of a K-CFM (module docstring).

    Args:
        n_keypoints, keypoint_dim, action_dim, n_obs: the layout (``K``, ``D``, ``A``, observation frames).
        goal_frame: ``{"keypoints": [...], "template": [[x, y], ...]}``, the goal's keypoint indices and where each
            lies in its body frame (:func:`~.frames.check_goal_frame`); None: the world frame.
        relative: actions as offsets from the agent, the last keypoint (2-D).
        origin: the index of the keypoint that keypoints and the actions' positions are taken relative to; None: off.
    """

    def __init__(self, n_keypoints: int, keypoint_dim: int, action_dim: int, n_obs: int, goal_frame: dict | None = None,
                 relative: bool = False, origin: int | None = None) -> None:  # fmt: skip
        super().__init__()
        check_frames(goal_frame, relative, origin, n_keypoints, keypoint_dim, action_dim)
        self.n_keypoints, self.keypoint_dim, self.action_dim, self.n_obs = n_keypoints, keypoint_dim, action_dim, n_obs
        self.goal_frame, self.relative, self.origin = goal_frame, bool(relative), origin
        self.register_buffer("kp_mean", torch.zeros(keypoint_dim * n_keypoints))
        self.register_buffer("kp_std", torch.ones(keypoint_dim * n_keypoints))
        self.register_buffer("action_center", torch.zeros(action_dim))
        self.register_buffer("action_scale", torch.ones(action_dim))
        self.register_buffer("stats_set", torch.tensor(False))

    @property
    def fitted(self) -> bool:
        """Whether the statistics were fitted (or loaded)."""
        return bool(self.stats_set)

    # ------------------------------------------------------------------------------------------- fitting

    def fit(self, keypoints, chunks, mask=None) -> None:
        """Fit the statistics to world-frame ``keypoints [N, K, D]`` and their action ``chunks [N, H, A]`` (or single
        actions ``[N, A]``), counting only the steps where ``mask [N, H]`` is true (all when None); module docstring.

        Raises:
            ValueError: shapes that do not fit the layout, an all-false mask, or NaN / inf in the data (rows named).
        """
        kp, act = _float64(keypoints), _float64(chunks)
        k, a, d = self.n_keypoints, self.action_dim, self.keypoint_dim
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
        flat = self.stats_frame(kp[:, None])[:, 0].reshape(len(kp), -1)
        std = flat.std(0, unbiased=False)
        real = act[mask]
        lo, hi = real.min(0).values, real.max(0).values
        half = (hi - lo) / 2
        with torch.no_grad():
            self.kp_mean.copy_(flat.mean(0))
            self.kp_std.copy_(torch.where(std < _MIN_STD, torch.ones_like(std), std))
            self.action_center.copy_((hi + lo) / 2)
            self.action_scale.copy_(torch.where(half < _MIN_HALF_RANGE, torch.zeros_like(half), half))
            self.stats_set.fill_(True)

    # -------------------------------------------------------------------------------------------- frames

    def goal_pose(self, keypoints: torch.Tensor) -> Frame:
        """The goal's frame ``(R [B, 2, 2], p [B, 2])`` in keypoint frames ``[B, K, 2]``: the rigid (Kabsch) fit of
        the ``goal_frame`` template onto the goal's keypoints (:func:`~kpflow.geometry.alignment.fit_affine`)."""
        goal = keypoints[:, self.goal_frame["keypoints"]]
        template = torch.as_tensor(self.goal_frame["template"], dtype=goal.dtype, device=goal.device)
        return fit_affine(template.expand_as(goal), goal, "rigid")

    def pose(self, history: torch.Tensor) -> Frame | None:
        """The current (last) frame's :meth:`goal_pose` of keypoint frames ``[B, n_obs, K, D]``; None without a goal frame."""
        return None if self.goal_frame is None else self.goal_pose(history[:, -1])

    def stats_frame(self, history: torch.Tensor, pose: Frame | None = None) -> torch.Tensor:
        """World keypoint frames ``[B, n_obs, K, D]`` (float64) in the frame the statistics are in: the current
        frame's goal frame (``pose``: its :meth:`goal_pose`, when the caller has it), relative to the current frame's
        ``origin`` keypoint, or as they are."""
        kp = history.to(torch.float64)
        if self.goal_frame is not None:
            kp = to_frame(kp.flatten(1, 2), *(self.goal_pose(kp[:, -1]) if pose is None else pose)).reshape(kp.shape)
        elif self.origin is not None:
            kp = kp - kp[:, -1, self.origin][:, None, None]
        return kp

    def action_frame(self, keypoints: torch.Tensor, pose: Frame | None = None) -> Frame | None:
        """The rigid frame ``(R [B, D, D], p [B, D])`` actions are predicted in, for keypoints ``[B, K, D]``.

        ``R`` is the goal's rotation with ``goal_frame`` (else the identity), ``p`` the agent (the last keypoint) with
        ``relative`` (else the goal's origin, or 0); with ``origin``: ``(I, the origin keypoint)``, applied to the
        actions' first ``D`` values. None when all are off: actions stay in world coordinates.
        """
        kp = keypoints.to(torch.float64)
        if self.origin is not None:
            d = self.keypoint_dim
            return torch.eye(d, dtype=kp.dtype, device=kp.device).expand(len(kp), d, d), kp[:, self.origin]
        if self.goal_frame is None and not self.relative:
            return None
        if self.goal_frame is not None:
            rot, origin = self.goal_pose(kp) if pose is None else pose
        else:
            rot = torch.eye(2, dtype=kp.dtype, device=kp.device).expand(len(kp), 2, 2)
            origin = torch.zeros_like(kp[:, 0])
        return rot, kp[:, -1] if self.relative else origin

    # ------------------------------------------------------------------------------------- normalisation

    def condition(self, stats_frame: torch.Tensor) -> torch.Tensor:
        """The network's condition ``c [B, n_obs K D]`` (float32) of keypoint frames already in the statistics'
        frame (:meth:`stats_frame`): standardised, concatenated oldest first."""
        b, n = stats_frame.shape[:2]
        return ((stats_frame.reshape(b, n, -1) - self.kp_mean.double()) / self.kp_std.double()).reshape(b, -1).float()

    def normalise_actions(self, actions: torch.Tensor, frame: Frame | None = None) -> torch.Tensor:
        """World actions ``[B, H, A]`` to the network's space: into the action ``frame`` (if given), then to [-1, 1]
        (a constant dimension, scale 0, to 0)."""
        a = actions.to(torch.float64)
        if frame is not None:
            a = to_frame(a, *frame)
        scale = self.action_scale.double()
        return ((a - self.action_center.double()) / torch.where(scale == 0, 1.0, scale)).float()

    def denormalise_actions(self, x: torch.Tensor, frame: Frame | None = None) -> torch.Tensor:
        """The inverse of :meth:`normalise_actions`: network-space chunks ``[B, H, A]`` to world actions (float32); a
        constant dimension comes out as its constant."""
        a = x.to(torch.float64) * self.action_scale.double() + self.action_center.double()
        if frame is not None:
            a = from_frame(a, *frame)
        return a.float()

    # ------------------------------------------------------------------------------------------- checks

    def check_keypoints(self, keypoints, device: torch.device | str = "cpu") -> torch.Tensor:
        """Keypoints as a finite float64 tensor ``[B, n_obs, K, D]`` on ``device``.

        Accepted: ``[B, n_obs, K, D]``; one history ``[n_obs, K, D]``; and, when ``n_obs = 1``, one frame ``[K, D]``
        or a batch of frames ``[B, K, D]``. Raises ``ValueError`` naming the shape wanted, or the items not finite.
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
        k, n, d, shape = self.n_keypoints, self.n_obs, self.keypoint_dim, tuple(kp.shape)
        if kp.ndim == 2 and n == 1:
            kp = kp[None, None]
        elif kp.ndim == 3:
            kp = kp[:, None] if n == 1 else kp[None]
        if kp.ndim != 4 or kp.shape[1:] != (n, k, d) or len(kp) == 0:
            single = f"[{k}, {d}], [B, {k}, {d}] or " if n == 1 else ""
            raise ValueError(
                f"keypoints must have shape {single}[{n}, {k}, {d}] or [B, {n}, {k}, {d}] (n_obs={n} frames) with B >= 1; got {shape}"
            )
        kp = kp.to(device, torch.float64)
        bad = ~torch.isfinite(kp).reshape(len(kp), -1).all(-1)
        if bad.any():
            raise ValueError(f"keypoints contain NaN or inf (batch items {torch.nonzero(bad).flatten()[:10].tolist()})")
        return kp

    def keypoint_box(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The box ``(lo [D], hi [D])`` (float64) of the training keypoints in the statistics' frame: per dimension,
        the least ``mean - 3 std`` and the largest ``mean + 3 std`` over every keypoint's statistics."""
        d = self.keypoint_dim
        mean, std = self.kp_mean.double().reshape(-1, d), self.kp_std.double().reshape(-1, d)
        return (mean - _BOX_STDS * std).min(0).values, (mean + _BOX_STDS * std).max(0).values

    def check_range(self, kp: torch.Tensor, stats_frame: torch.Tensor, input_margin: float | None) -> None:
        """Refuse checked keypoint frames ``kp`` (and the same frames in the statistics' frame) with a coordinate
        outside ``[lo - m w, hi + m w]`` (``(lo, hi)`` the :meth:`keypoint_box`, ``w = hi - lo``, ``m =
        input_margin``): in the world and, with ``goal_frame``, in the goal's frame too; relative to the origin
        keypoint alone with ``origin``. Nothing is checked when ``input_margin`` is None or the statistics were never
        fitted (an untrained model has no range).

        Raises:
            ValueError: naming the first keypoint outside, its coordinates, the accepted interval and the box.
        """
        if input_margin is None or not self.fitted:
            return
        lo, hi = self.keypoint_box()
        lo_ok, hi_ok = lo - input_margin * (hi - lo), hi + input_margin * (hi - lo)
        if self.origin is not None:  # statistics relative to a keypoint say nothing of the world
            frames = [(f" relative to keypoint {self.origin}", stats_frame)]
        else:
            frames = [("", kp)] + ([(" in the goal's frame", stats_frame)] if self.goal_frame is not None else [])
        for where, x in frames:
            outside = ~((x >= lo_ok) & (x <= hi_ok))  # NaN (a frame that overflowed) counts as outside
            if outside.any():
                b, f, k, d = (int(i) for i in torch.nonzero(outside)[0])
                frame = f" of observation frame {f}" if self.n_obs > 1 else ""
                at = ", ".join(f"{v:.4g}" for v in kp[b, f, k].tolist())
                raise ValueError(
                    f"the observation is far outside the range this K-CFM was trained on: keypoint {k}{frame} at ({at}) has "
                    f"coordinate {d} = {float(x[b, f, k, d]):.4g}{where}, outside the accepted [{float(lo_ok[d]):.4g}, "
                    f"{float(hi_ok[d]):.4g}] (the training keypoints' box [{float(lo[d]):.4g}, {float(hi[d]):.4g}], mean +- "
                    f"{_BOX_STDS:g} std, widened by input_margin={input_margin:g} times its extent on each side); refusing to act on it"
                )
