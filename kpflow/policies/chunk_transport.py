"""Policy transportation: a near demonstrated chunk, carried into the current scene by a keypoint map.

With ``S`` the chosen source's keypoints and ``T`` the observed ones, fit ``phi`` with ``phi(S) ~= T`` and execute
the source's chunk of absolute targets carried through ``phi`` (the paper's offline transport applied to one chunk at
a time, :func:`transport_chunk`): each target position ``p -> phi(p)``; where the actions hold a 6-D rotation after
the position (the robosuite tasks' end-effector targets, :class:`~.base.PolicyLayout` ``rotation``), ``R ->
polar(J(p)) R`` with ``J`` phi's Jacobian (:func:`kpflow.transport.transport_orientations`); anything after that (a
gripper command) is kept.

Which keypoints the map is fitted on (``fit_on``; all by default). In Push-T, fitting the block and the agent
alone (``fit_on=block_agent`` in ``kpflow/conf/policy/transport.yaml``) carries the chunk rigidly with the block
and bends it only towards the agent. Fitting the goal too makes the map bend between the block's and the goal's
keypoints, which nearly coincide at the end of a push (and coincide exactly at the end of a demonstration read with
hindsight goals, :mod:`kpflow.data.hindsight`), so the chunk is carried part with the block and part with the goal.
The goal is matched by the search instead: in the block's frame it picks a source whose goal lies where the observed
one does, so the chunk's push relative to the block is the one to make.

Choosing the source: :class:`~.source_choice.SourceChoice` (the nearest, or a draw among the nearest, and stuck
detection). ``max_step`` clips each executed step: target ``j`` moves at most that far per axis from target
``j - 1`` (from the robot's observed keypoints, their centroid, for the first), as the authors' code clips Push-T's
actions to +-5 px.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import torch

from kpflow.core.policy import PolicyLayout

from ..data.source_index import SourceIndex
from ..geometry.rotations import matrix_to_rot6d, rot6d_to_matrix
from ..maps import ILWRMap
from ..maps.base import TransportMap
from ..transport import transport_orientations
from .source_choice import SourceChoice


def fitted_keypoints(fit_on: Sequence[int] | None, k: int) -> slice | np.ndarray:
    """The rows of a ``[k, D]`` keypoint set that ``fit_on`` names (all for None), checked: distinct, in ``0..k-1``."""
    if fit_on is None:
        return slice(None)
    if not (len(fit_on) >= 1 and len(set(fit_on)) == len(fit_on) and all(0 <= i < k for i in fit_on)):
        raise ValueError(f"fit_on must list distinct keypoint indices in 0..{k - 1}, got {fit_on!r}")
    return np.asarray(fit_on, np.int64)


def transport_chunk(phi: TransportMap, chunk: np.ndarray, dim: int, rotation: bool = False) -> np.ndarray:
    """A chunk of absolute targets ``[H, A]`` carried through ``phi`` (module docstring): columns ``:dim`` are
    positions (``phi(p)``), then with ``rotation`` a 6-D rotation (``polar(J(p)) R``), the rest is kept (float64)."""
    chunk = np.asarray(chunk, np.float64)
    out = chunk.copy()
    x = torch.from_numpy(np.ascontiguousarray(chunk[:, :dim]))
    with torch.no_grad():
        out[:, :dim] = phi(x).to(torch.float64).numpy()
        if rotation:
            rot = torch.from_numpy(rot6d_to_matrix(chunk[:, dim : dim + 6]))
            out[:, dim : dim + 6] = matrix_to_rot6d(transport_orientations(phi, x, rot).numpy())
    return out


def robot_and_rotation(layout: PolicyLayout | None, k: int) -> tuple[np.ndarray, bool]:
    """The robot's keypoint indices and whether actions carry a rotation, from the task's ``layout`` (``ValueError``
    without one, or when it names another number of keypoints than the ``k`` of the source index)."""
    if layout is None:
        raise ValueError(
            "a transporting policy needs the task's PolicyLayout (layout=task.policy_layout): which keypoints are the robot's"
        )
    if layout.n_keypoints != k:
        raise ValueError(f"the layout names {layout.n_keypoints} keypoints; the source index holds {k}")
    robot = layout.indices("robot")
    if not robot:
        raise ValueError("the layout names no robot keypoints (role 'robot')")
    return np.asarray(robot), layout.rotation


def clip_steps(start: np.ndarray, targets: np.ndarray, max_step: float) -> np.ndarray:
    """Targets ``[H, A]`` with each step clipped per axis: ``c_0 = start + clip(t_0 - start, -m, m)``,
    ``c_j = c_{j-1} + clip(t_j - c_{j-1}, -m, m)``."""
    out, prev = np.empty_like(targets), np.asarray(start, dtype=targets.dtype)
    for j, t in enumerate(targets):
        prev = prev + np.clip(t - prev, -max_step, max_step)
        out[j] = prev
    return out


class TransportPolicy:
    """A source chosen by :class:`SourceChoice`, then its chunk transported by a map from ``make_map()`` (ILWR)
    fitted on the keypoints ``fit_on`` (module docstring).

    Args:
        execute: how many of the chunk's targets :meth:`act` returns.
        max_step: clip every executed step to this distance per axis (the keypoints' unit: Push-T px; None: no clipping).
        fit_on: indices of the keypoints the map is fitted on (None: all).
        layout: the task's :class:`~.base.PolicyLayout` (the robot's keypoints, whether actions carry a rotation).
        choice: :class:`SourceChoice`'s options (``candidates``, ``temperature``, ``stuck_decisions``, ``stuck_distance``,
            ``stuck_candidates``).
    """

    def __init__(
        self,
        index: SourceIndex,
        make_map: Callable[[], TransportMap] = ILWRMap,
        execute: int = 20,
        max_step: float | None = None,
        fit_on: Sequence[int] | None = None,
        layout: PolicyLayout | None = None,
        **choice,
    ):
        if not 1 <= execute <= index.chunks.shape[1]:
            raise ValueError(f"execute must be in 1..{index.chunks.shape[1]} (the chunk length), got {execute}")
        if max_step is not None and not (np.isfinite(max_step) and max_step > 0):
            raise ValueError(f"max_step must be a positive number or None, got {max_step!r}")
        self.source = SourceChoice(index, **choice)
        self.fit_on = fitted_keypoints(fit_on, index.keypoints.shape[1])
        self.index, self.make_map, self.execute, self.max_step = index, make_map, execute, max_step
        self.robot, self.rotation = robot_and_rotation(layout, index.keypoints.shape[1])
        self.last_source: int | None = None
        self.last_map: TransportMap | None = None

    def reset(self, seed: int | None = None) -> None:
        """Reseed the source draw with ``seed`` (0 when None)."""
        self.source.reset(seed)
        self.last_source, self.last_map = None, None

    def act(self, obs: dict) -> np.ndarray:
        target = np.asarray(obs["keypoints"], dtype=np.float64)
        i = self.source.choose(target)
        source = self.index.keypoints[i].astype(np.float64)
        phi = self.make_map().fit(torch.from_numpy(source[self.fit_on]), torch.from_numpy(target[self.fit_on]))
        self.last_source, self.last_map = i, phi
        moved = transport_chunk(phi, self.index.chunks[i, : self.execute], source.shape[1], self.rotation)
        if self.max_step is not None:  # the positions, from where the robot's keypoints are now
            dim = source.shape[1]
            moved[:, :dim] = clip_steps(target[self.robot].mean(0), moved[:, :dim], self.max_step)
        return moved
