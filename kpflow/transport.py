"""What moves through a transportation map phi (any :class:`~kpflow.maps.base.TransportMap`).

With J(x) = d phi / d x:

- positions        x  -> phi(x)
- velocities       v  -> J(x) v                          (push-forward of a tangent vector)
- orientations     R  -> polar(J(x)) R                   (polar(J) = U V^T for J = U S V^T: the rotation nearest J)
- covariances      S  -> J(x) S J(x)^T                   (linearised push-forward of a Gaussian)
- stiffness        K  -> Q K Q^T, Q = polar(J(x))        (``mode="rotation"``: keeps the stiffness magnitudes,
                                                          as in the paper)
                   K  -> J^-T K J^-1                     (``mode="covector"``: keeps the elastic energy
                                                          1/2 dx^T K dx invariant)
- uncertainty      std(x) = sqrt(var(x)) from ``predict``; a k-sigma band is mean +- k std.
- samples          n maps drawn from the map's posterior (or ensemble), each applied to the whole trajectory.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from kpflow.geometry.rotations import matrix_to_quat, nearest_rotation, quat_to_matrix
from kpflow.maps.base import TransportMap


def transport_positions(phi: TransportMap, x: torch.Tensor) -> torch.Tensor:
    """phi(x) for ``x [..., D]``."""
    return phi(x)


def transport_velocities(
    phi: TransportMap, x: torch.Tensor, v: torch.Tensor, jac: torch.Tensor | None = None
) -> torch.Tensor:
    """J(x) v for velocities ``v [..., D]`` at positions ``x [..., D]``."""
    jac = phi.jacobian(x) if jac is None else jac
    return (jac @ v.to(jac).unsqueeze(-1)).squeeze(-1)


def transport_orientations(
    phi: TransportMap, x: torch.Tensor, rot: torch.Tensor, jac: torch.Tensor | None = None
) -> torch.Tensor:
    """polar(J(x)) R for rotation matrices ``rot [..., D, D]`` at positions ``x``."""
    jac = phi.jacobian(x) if jac is None else jac
    return nearest_rotation(jac) @ rot.to(jac)


def transport_quaternions(phi: TransportMap, x: torch.Tensor, quat: torch.Tensor) -> torch.Tensor:
    """As :func:`transport_orientations` for unit quaternions ``[..., 4]`` (x, y, z, w) in 3-D."""
    return matrix_to_quat(transport_orientations(phi, x, quat_to_matrix(quat)))


def transport_covariances(
    phi: TransportMap, x: torch.Tensor, cov: torch.Tensor, jac: torch.Tensor | None = None
) -> torch.Tensor:
    """J S J^T for covariance matrices ``cov [..., D, D]``."""
    jac = phi.jacobian(x) if jac is None else jac
    return jac @ cov.to(jac) @ jac.transpose(-1, -2)


def transport_stiffness(
    phi: TransportMap, x: torch.Tensor, stiffness: torch.Tensor, mode: str = "rotation", jac: torch.Tensor | None = None
) -> torch.Tensor:
    """Stiffness matrices ``[..., D, D]``: Q K Q^T (``"rotation"``) or J^-T K J^-1 (``"covector"``)."""
    jac = phi.jacobian(x) if jac is None else jac
    k = stiffness.to(jac)
    if mode == "rotation":
        q = nearest_rotation(jac)
        return q @ k @ q.transpose(-1, -2)
    if mode == "covector":
        jinv = torch.linalg.inv(jac)
        return jinv.transpose(-1, -2) @ k @ jinv
    raise ValueError(f"unknown stiffness mode {mode!r}; choose 'rotation' or 'covector'")


@dataclass
class TransportedTrajectory:
    """A demonstration after transport; ``None`` fields were not given or not asked for."""

    positions: torch.Tensor  # [T, D]
    std: torch.Tensor  # [T, D]
    velocities: torch.Tensor | None = None  # [T, D]
    orientations: torch.Tensor | None = None  # [T, D, D]
    stiffness: torch.Tensor | None = None  # [T, D, D]
    samples: torch.Tensor | None = None  # [n, T, D]

    def band(self, k: float = 2.0) -> tuple[torch.Tensor, torch.Tensor]:
        """Lower and upper edges of the k-sigma band."""
        return self.positions - k * self.std, self.positions + k * self.std


def transport_trajectory(
    phi: TransportMap,
    positions: torch.Tensor,
    velocities: torch.Tensor | None = None,
    orientations: torch.Tensor | None = None,
    stiffness: torch.Tensor | None = None,
    stiffness_mode: str = "rotation",
    n_samples: int = 0,
    generator: torch.Generator | None = None,
) -> TransportedTrajectory:
    """Transport a whole demonstration (one Jacobian evaluation shared by all derivative quantities)."""
    mean, var = phi.predict(positions)
    need_jac = velocities is not None or orientations is not None or stiffness is not None
    jac = phi.jacobian(positions) if need_jac else None
    return TransportedTrajectory(
        positions=mean,
        std=var.sqrt(),
        velocities=None if velocities is None else transport_velocities(phi, positions, velocities, jac),
        orientations=None if orientations is None else transport_orientations(phi, positions, orientations, jac),
        stiffness=None if stiffness is None else transport_stiffness(phi, positions, stiffness, stiffness_mode, jac),
        samples=phi.sample(positions, n_samples, generator) if n_samples > 0 else None,
    )
