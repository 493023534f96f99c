"""Synthetic demonstrator: a smooth, human-like reaching motion between two frames.

The path is a cubic Hermite curve from the start frame's origin to the goal frame's
origin whose end tangents are the frames' +x axes (leave along the start's x axis,
arrive along the goal's x axis -- the approach direction), plus a smooth random
lateral wiggle that vanishes, with its slope, at both ends. It is timed with a
minimum-jerk profile, so the speed is bell-shaped and zero at both ends.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from kpflow.geometry.rotations import rotation_2d, so3_exp, so3_log

from .frames import Frame

__all__ = ["DemonstratedMotion", "demonstrate", "minimum_jerk"]


@dataclass
class DemonstratedMotion:
    """One demonstrated trajectory of T samples in D = 2 or 3 dimensions.

    positions [T, D], velocities [T, D] (d positions / d times), orientations [T, D, D]
    (rotation matrices), times [T] (increasing, seconds).
    """

    positions: torch.Tensor
    velocities: torch.Tensor
    orientations: torch.Tensor
    times: torch.Tensor

    def __post_init__(self):
        p, v, R, t = self.positions, self.velocities, self.orientations, self.times
        if p.ndim != 2 or p.shape[1] not in (2, 3):
            raise ValueError(f"positions must have shape [T, D] with D = 2 or 3, got {tuple(p.shape)}")
        T, D = p.shape
        if v.shape != (T, D):
            raise ValueError(f"velocities must have shape {(T, D)}, got {tuple(v.shape)}")
        if R.shape != (T, D, D):
            raise ValueError(f"orientations must have shape {(T, D, D)}, got {tuple(R.shape)}")
        if t.shape != (T,):
            raise ValueError(f"times must have shape {(T,)}, got {tuple(t.shape)}")
        for name, x in (("positions", p), ("velocities", v), ("orientations", R), ("times", t)):
            if not torch.isfinite(x).all():
                raise ValueError(f"{name} contains NaN or inf")

    def __len__(self) -> int:
        return self.positions.shape[0]

    @property
    def dim(self) -> int:
        return self.positions.shape[1]

    def to(self, dtype: torch.dtype) -> "DemonstratedMotion":
        return DemonstratedMotion(
            *(x.to(dtype) for x in (self.positions, self.velocities, self.orientations, self.times))
        )


def minimum_jerk(u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Minimum-jerk phase ``s(u) = 10 u^3 - 15 u^4 + 6 u^5`` and ``ds/du = 30 u^2 (1 - u)^2`` on [0, 1]."""
    return u**3 * (10 - 15 * u + 6 * u**2), 30 * u**2 * (1 - u) ** 2


def _lateral_directions(chord: torch.Tensor) -> torch.Tensor:
    """Unit vectors orthogonal to the unit vector ``chord`` [D]: [D-1, D]."""
    if chord.shape[0] == 2:
        return torch.stack([-chord[1], chord[0]])[None]
    helper = torch.zeros_like(chord)
    helper[torch.argmin(chord.abs())] = 1.0
    n1 = torch.linalg.cross(chord, helper)
    n1 = n1 / torch.linalg.vector_norm(n1)
    return torch.stack([n1, torch.linalg.cross(chord, n1)])


def demonstrate(
    start: Frame,
    goal: Frame,
    n: int = 200,
    generator: torch.Generator | None = None,
    wiggle: float = 0.1,
    duration: float = 1.0,
    tangent_scale: float = 1.0,
    n_harmonics: int = 3,
) -> DemonstratedMotion:
    """Reaching demonstration from ``start``'s origin to ``goal``'s origin, ``n`` samples.

    With ``p0, p1`` the frame origins, ``x0, x1`` their +x axes, ``L = tangent_scale *
    |p1 - p0|`` and the phase ``s`` in [0, 1], the path is

        p(s) = h00(s) p0 + h10(s) L x0 + h01(s) p1 + h11(s) L x1               (cubic Hermite)
               + wiggle |p1 - p0| 16 s^2 (1-s)^2 sum_j n_j sum_k c_jk sin(pi k s + phi_jk)

    with ``h00 = 2s^3 - 3s^2 + 1``, ``h10 = s^3 - 2s^2 + s``, ``h01 = -2s^3 + 3s^2``,
    ``h11 = s^3 - s^2``; ``n_j`` the D-1 unit directions orthogonal to the chord
    ``p1 - p0``; ``k = 1..n_harmonics``, amplitudes ``c_jk ~ U(-1, 1) / n_harmonics`` and
    phases ``phi_jk ~ U(0, 2 pi)`` drawn from ``generator`` (so the lateral excursion is at
    most ``wiggle |p1 - p0|``). The envelope ``16 s^2 (1-s)^2`` makes the wiggle and its
    slope vanish at both ends, so ``p'(0) = L x0`` and ``p'(1) = L x1`` exactly.

    Timing: ``t = duration * u`` with ``u`` uniform on [0, 1] and ``s = 10u^3 - 15u^4 + 6u^5``
    (minimum jerk). Velocities are analytic: ``v = p'(s) * ds/du / duration`` (zero at
    both ends). Orientations: ``R(s) = R0 exp(s log(R0^T R1))`` -- in 2-D the heading
    angle interpolated along the shortest arc, in 3-D slerp via axis-angle.

    Computed in float64 (the random draws too) and returned in the promoted dtype of
    the two frames; a deterministic function of the generator's state (the global RNG
    when ``generator`` is None). Note: because the speed starts and ends at zero, the
    first and last displacements are tiny (~1e-5 |p1 - p0| for n = 200); in float32
    their direction is dominated by rounding -- use ``velocities[1]`` / ``velocities[-2]``
    or float64 frames for end directions.
    """
    if not isinstance(start, Frame) or not isinstance(goal, Frame):
        raise ValueError("start and goal must be Frame instances")
    if start.dim != goal.dim:
        raise ValueError(f"start and goal must have the same dimension, got {start.dim} and {goal.dim}")
    if n < 2:
        raise ValueError(f"a demonstration needs n >= 2 samples, got {n}")
    if not duration > 0:
        raise ValueError(f"duration must be positive, got {duration}")
    if not tangent_scale > 0:
        raise ValueError(f"tangent_scale must be positive, got {tangent_scale}")
    if wiggle < 0 or n_harmonics < 1:
        raise ValueError(f"need wiggle >= 0 and n_harmonics >= 1, got {wiggle} and {n_harmonics}")
    out_dtype = torch.promote_types(start.dtype, goal.dtype)
    dtype = torch.float64  # computed in float64, returned in the frames' dtype
    D = start.dim
    p0, p1 = start.position.to(dtype), goal.position.to(dtype)
    R0, R1 = start.rotation.to(dtype), goal.rotation.to(dtype)
    dist = torch.linalg.vector_norm(p1 - p0)
    if dist <= 1e3 * torch.finfo(dtype).eps:
        raise ValueError("start and goal frames are at the same position; nothing to reach")
    L = tangent_scale * dist

    u = torch.linspace(0.0, 1.0, n, dtype=dtype)
    s, ds_du = minimum_jerk(u)
    sc = s[:, None]

    # Cubic Hermite curve and its derivative w.r.t. s.
    h = torch.cat([2 * sc**3 - 3 * sc**2 + 1, sc**3 - 2 * sc**2 + sc, -2 * sc**3 + 3 * sc**2, sc**3 - sc**2], 1)
    dh = torch.cat([6 * sc**2 - 6 * sc, 3 * sc**2 - 4 * sc + 1, -6 * sc**2 + 6 * sc, 3 * sc**2 - 2 * sc], 1)
    ctrl = torch.stack([p0, L * R0[:, 0], p1, L * R1[:, 0]])  # [4, D]
    pos = h @ ctrl
    dpos = dh @ ctrl

    # Lateral wiggle: envelope e(s) = 16 s^2 (1-s)^2 times a few random low-frequency sines.
    if wiggle > 0:
        normals = _lateral_directions((p1 - p0) / dist)  # [D-1, D]
        amp = (2 * torch.rand(D - 1, n_harmonics, generator=generator, dtype=dtype) - 1) / n_harmonics
        phase = 2 * math.pi * torch.rand(D - 1, n_harmonics, generator=generator, dtype=dtype)
        freq = math.pi * torch.arange(1, n_harmonics + 1, dtype=dtype)
        arg = freq * s[:, None, None] + phase  # [T, D-1, K]
        g = (amp * torch.sin(arg)).sum(-1)  # [T, D-1]
        dg = (amp * freq * torch.cos(arg)).sum(-1)
        e = 16 * s**2 * (1 - s) ** 2
        de = 32 * s * (1 - s) * (1 - 2 * s)
        scale = wiggle * dist
        pos = pos + scale * (e[:, None] * g) @ normals
        dpos = dpos + scale * (de[:, None] * g + e[:, None] * dg) @ normals

    # Exact end points (the Hermite basis reproduces them up to rounding).
    pos[0], pos[-1] = p0, p1
    velocities = dpos * (ds_du / duration)[:, None]

    # Orientations R(s) = R0 exp(s log(R0^T R1)).
    if D == 2:
        rel = R0.T @ R1
        dtheta = torch.atan2(rel[1, 0], rel[0, 0])  # shortest arc, in (-pi, pi]
        orientations = R0 @ rotation_2d(s * dtheta)
    else:
        omega = so3_log(R0.T @ R1)
        orientations = R0 @ so3_exp(s[:, None] * omega)
    orientations[0], orientations[-1] = R0, R1

    return DemonstratedMotion(pos, velocities, orientations, duration * u).to(out_dtype)
