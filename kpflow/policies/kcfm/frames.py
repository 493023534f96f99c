"""The K-CFM's frames (processors apart from the network): the goal's frame, the robot-relative frame, and the
checks of what a config asks of them. Points go into a frame ``(R, o)`` as ``R^T (x - o)`` and back as ``R x + o``."""

from __future__ import annotations

import numpy as np
import torch


def check_goal_frame(goal_frame, n_keypoints: int) -> None:
    """Raise ``ValueError`` unless ``goal_frame`` is None or ``{"keypoints": [G distinct indices in 0..K-1],
    "template": [G points [x, y]]}`` with G >= 2, finite coordinates and a template that is not one point (its
    rotation would be undetermined)."""
    if goal_frame is None:
        return
    form = '{"keypoints": [G indices], "template": [G points [x, y]]}'
    if not isinstance(goal_frame, dict) or set(goal_frame) != {"keypoints", "template"}:
        raise ValueError(
            f"goal_frame must be None or {form} (the goal's keypoints and their body frame); got {goal_frame!r}"
        )
    index, template = goal_frame["keypoints"], np.asarray(goal_frame["template"], dtype=np.float64)
    if not (isinstance(index, (list, tuple)) and all(isinstance(i, int) and not isinstance(i, bool) for i in index)):
        raise ValueError(f"goal_frame['keypoints'] must list keypoint indices; got {index!r}")
    if len(index) < 2 or len(set(index)) != len(index) or not all(0 <= i < n_keypoints for i in index):
        raise ValueError(
            f"goal_frame['keypoints'] must list at least 2 distinct indices in 0..{n_keypoints - 1}; got {index}"
        )
    if template.shape != (len(index), 2) or not np.isfinite(template).all():
        raise ValueError(
            f"goal_frame['template'] must hold {len(index)} finite points [x, y], one per goal keypoint; got shape {template.shape}"
        )
    if np.ptp(template, axis=0).max() == 0:
        raise ValueError("goal_frame['template'] is one point: the goal's rotation would be undetermined")


def check_frames(goal_frame, relative: bool, origin, n_keypoints: int, keypoint_dim: int, action_dim: int) -> None:
    """Raise ``ValueError`` unless the frames keypoints and actions are expressed in fit the layout: ``goal_frame``
    (:func:`check_goal_frame`) and ``relative`` are planar; ``origin`` is a keypoint index, alone, with actions that
    start with a position."""
    check_goal_frame(goal_frame, n_keypoints)
    if (goal_frame is not None or relative) and keypoint_dim != 2:
        raise ValueError(f"goal_frame and relative are planar: they need keypoint_dim=2; got {keypoint_dim}")
    if goal_frame is not None and action_dim != 2:
        raise ValueError(f"goal_frame maps actions into the goal's plane: it needs 2-D actions; got {action_dim}")
    if relative and action_dim != 2:
        raise ValueError(
            f"relative actions are offsets from the agent keypoint: they need 2-D actions; got {action_dim}"
        )
    if origin is None:
        return
    if (
        isinstance(origin, bool)
        or not isinstance(origin, (int, np.integer))
        or not -n_keypoints <= origin < n_keypoints
    ):
        raise ValueError(f"origin must be a keypoint index in [-{n_keypoints}, {n_keypoints}); got {origin!r}")
    if goal_frame is not None or relative:
        raise ValueError(
            "origin translates keypoints and actions to one keypoint: use it without goal_frame and relative"
        )
    if action_dim < keypoint_dim:
        raise ValueError(
            f"origin needs actions that start with a position of keypoint_dim={keypoint_dim} values; got action_dim={action_dim}"
        )


def to_frame(points: torch.Tensor, rot: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:
    """World points ``[B, N, D]`` into the frame ``(R [B, D, D], p [B, D])``: ``R^T (x - p)`` (like
    ``geometry.to_body``); rows with more than ``D`` values (an action's rotation, gripper) keep the rest as they are."""
    d = rot.shape[-1]
    moved = (points[..., :d] - origin[:, None]) @ rot
    return moved if points.shape[-1] == d else torch.cat([moved, points[..., d:]], -1)


def from_frame(points: torch.Tensor, rot: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:
    """Frame points ``[B, N, D(+)]`` back to the world: ``R q + p`` (the inverse of :func:`to_frame`)."""
    d = rot.shape[-1]
    moved = points[..., :d] @ rot.mT + origin[:, None]
    return moved if points.shape[-1] == d else torch.cat([moved, points[..., d:]], -1)
