"""Reference frames (rigid poses in 2-D or 3-D) and their keypoints.

A :class:`Frame` is a pose ``(p, R)``: position ``p`` [D] and rotation ``R`` [D, D]
(columns are the frame's axes in world coordinates). It maps local points to world
points with ``x_world = R x_local + p``.

Following the keypoint-based policy transportation set-up (Franzese, Prakash and Kober, arXiv:2404.13458), every frame
is summarised by five keypoints rigidly attached to it (:func:`frame_keypoints`); a
scene of several frames by their concatenation (:func:`scene_keypoints`).

Rotation helpers (planar rotations, roll-pitch-yaw, SO(3) exp/log) live in :mod:`kpflow.geometry.rotations`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch

from kpflow.geometry.rotations import euler_to_matrix, float_dtype, rotation_2d

__all__ = [
    "Frame",
    "frame_keypoints",
    "scene_keypoints",
    "random_frame",
]


@dataclass(frozen=True)
class Frame:
    """Rigid pose: ``position`` [D] and ``rotation`` [D, D], D = 2 or 3.

    ``x_world = rotation @ x_local + position``. The rotation's columns are the frame's
    x, y (, z) axes in world coordinates. Inputs are converted to one floating dtype;
    the rotation must be orthonormal with determinant +1 (within a dtype-dependent
    tolerance).
    """

    position: torch.Tensor
    rotation: torch.Tensor

    def __post_init__(self):
        dtype = float_dtype(self.position, self.rotation)
        p = torch.as_tensor(self.position, dtype=dtype)
        R = torch.as_tensor(self.rotation, dtype=dtype)
        if p.ndim != 1 or p.shape[0] not in (2, 3):
            raise ValueError(f"Frame position must have shape [D] with D = 2 or 3, got {tuple(p.shape)}")
        D = p.shape[0]
        if R.shape != (D, D):
            raise ValueError(f"Frame rotation must have shape [{D}, {D}] to match the position, got {tuple(R.shape)}")
        if not (torch.isfinite(p).all() and torch.isfinite(R).all()):
            raise ValueError("Frame position and rotation must be finite (got NaN or inf)")
        tol = 1e-3 if torch.finfo(dtype).eps > 1e-10 else 1e-6
        if (R.T @ R - torch.eye(D, dtype=dtype)).abs().max() > tol:
            raise ValueError("Frame rotation is not orthonormal (R^T R != I)")
        if torch.linalg.det(R) < 0:
            raise ValueError("Frame rotation has determinant -1 (a reflection, not a rotation)")
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "rotation", R)

    # -- constructors -----------------------------------------------------------------
    @classmethod
    def from_2d(cls, x, y, theta, dtype: torch.dtype | None = None) -> "Frame":
        """Planar frame at ``(x, y)`` whose x axis makes angle ``theta`` (radians) with the world x axis."""
        dtype = float_dtype(x, y, theta, dtype=dtype)
        p = torch.stack([torch.as_tensor(x, dtype=dtype), torch.as_tensor(y, dtype=dtype)])
        return cls(p, rotation_2d(theta, dtype=dtype))

    @classmethod
    def from_3d(cls, position, rotation_matrix, dtype: torch.dtype | None = None) -> "Frame":
        """Spatial frame from a position [3] and a rotation matrix [3, 3]."""
        dtype = float_dtype(position, rotation_matrix, dtype=dtype)
        p = torch.as_tensor(position, dtype=dtype)
        R = torch.as_tensor(rotation_matrix, dtype=dtype)
        if p.shape != (3,) or R.shape != (3, 3):
            raise ValueError(
                f"from_3d needs position [3] and rotation [3, 3], got {tuple(p.shape)} and {tuple(R.shape)}"
            )
        return cls(p, R)

    @classmethod
    def from_euler_3d(cls, position, rpy, dtype: torch.dtype | None = None) -> "Frame":
        """Spatial frame from a position [3] and roll-pitch-yaw [3] (``R = Rz(yaw) Ry(pitch) Rx(roll)``)."""
        dtype = float_dtype(position, rpy, dtype=dtype)
        return cls.from_3d(position, euler_to_matrix(torch.as_tensor(rpy, dtype=dtype)), dtype=dtype)

    # -- properties -------------------------------------------------------------------
    @property
    def dim(self) -> int:
        return self.position.shape[0]

    @property
    def dtype(self) -> torch.dtype:
        return self.position.dtype

    @property
    def x_axis(self) -> torch.Tensor:
        """The frame's +x axis in world coordinates (first column of the rotation)."""
        return self.rotation[:, 0]

    @property
    def theta(self) -> torch.Tensor:
        """2-D only: heading angle ``atan2(R[1,0], R[0,0])``."""
        if self.dim != 2:
            raise ValueError("theta is only defined for 2-D frames")
        return torch.atan2(self.rotation[1, 0], self.rotation[0, 0])

    # -- operations -------------------------------------------------------------------
    def transform(self, points) -> torch.Tensor:
        """Local -> world: ``x_world = R x_local + p`` for ``points`` [..., D]."""
        points = torch.as_tensor(points)
        dtype = float_dtype(points, self.position)
        points = points.to(dtype)
        if points.shape[-1:] != (self.dim,):
            raise ValueError(f"points must have shape [..., {self.dim}], got {tuple(points.shape)}")
        return points @ self.rotation.to(dtype).T + self.position.to(dtype)

    def inverse_transform(self, points) -> torch.Tensor:
        """World -> local: ``x_local = R^T (x_world - p)`` for ``points`` [..., D]."""
        points = torch.as_tensor(points)
        dtype = float_dtype(points, self.position)
        points = points.to(dtype)
        if points.shape[-1:] != (self.dim,):
            raise ValueError(f"points must have shape [..., {self.dim}], got {tuple(points.shape)}")
        return (points - self.position.to(dtype)) @ self.rotation.to(dtype)

    def compose(self, other: "Frame") -> "Frame":
        """``self * other``: the pose ``(R1 R2, R1 p2 + p1)``, i.e. ``other`` expressed in world
        coordinates when ``other`` is given relative to ``self``. ``(a @ b).transform(x) ==
        a.transform(b.transform(x))``."""
        if other.dim != self.dim:
            raise ValueError(f"cannot compose a {self.dim}-D frame with a {other.dim}-D frame")
        dtype = torch.promote_types(self.dtype, other.dtype)
        return Frame(self.transform(other.position).to(dtype), self.rotation.to(dtype) @ other.rotation.to(dtype))

    __matmul__ = compose

    def inverse(self) -> "Frame":
        """``(R^T, -R^T p)``."""
        return Frame(-(self.rotation.T @ self.position), self.rotation.T.clone())

    def as_matrix(self) -> torch.Tensor:
        """Homogeneous matrix ``[[R, p], [0, 1]]`` of shape [D+1, D+1]."""
        M = torch.eye(self.dim + 1, dtype=self.dtype)
        M[: self.dim, : self.dim] = self.rotation
        M[: self.dim, self.dim] = self.position
        return M

    def to(self, dtype: torch.dtype) -> "Frame":
        return Frame(self.position.to(dtype), self.rotation.to(dtype))


def frame_keypoints(frame: Frame, size: float = 1.0) -> torch.Tensor:
    """Five keypoints rigidly attached to ``frame``, in world coordinates: [5, D].

    In local coordinates (``s = size``):

    * 2-D: ``[origin, +s x, +s y, -s x, -s y]``;
    * 3-D: ``[origin, +s x, +s y, +s z, -s x]``.

    i.e. row 0 is the frame origin, rows 1..D the points at ``+size`` along the axes, and
    the remaining rows points at ``-size`` (along -x, then -y in 2-D). The keypoints are
    ``frame.transform(local)``, so transforming the frame rigidly transforms them.
    """
    if not size > 0:
        raise ValueError(f"keypoint size must be positive, got {size}")
    D = frame.dim
    eye = torch.eye(D, dtype=frame.dtype)
    zero = torch.zeros(1, D, dtype=frame.dtype)
    if D == 2:
        local = torch.cat([zero, eye, -eye])
    else:
        local = torch.cat([zero, eye, -eye[:1]])
    return frame.transform(size * local)


def scene_keypoints(frames: Sequence[Frame], size: float = 1.0) -> torch.Tensor:
    """Keypoints of several frames, concatenated in order: [5 * len(frames), D].

    Rows ``5 i .. 5 i + 4`` are ``frame_keypoints(frames[i], size)``.
    """
    frames = list(frames)
    if not frames:
        raise ValueError("scene_keypoints needs at least one frame")
    if len({f.dim for f in frames}) != 1:
        raise ValueError("all frames of a scene must have the same dimension")
    dtype = frames[0].dtype
    for f in frames[1:]:
        dtype = torch.promote_types(dtype, f.dtype)
    return torch.cat([frame_keypoints(f.to(dtype), size) for f in frames])


def random_frame(
    generator: torch.Generator | None = None,
    dim: int = 2,
    workspace=1.0,
    dtype: torch.dtype | None = None,
) -> Frame:
    """Random pose: position uniform in the workspace box, rotation uniform.

    ``workspace`` is a half-width ``w`` (position uniform in ``[-w, w]^D``) or a pair
    ``(low, high)`` of scalars or [D] tensors (uniform in ``[low, high]``). The rotation
    is a uniform angle in ``[-pi, pi)`` in 2-D, and the rotation of a normalised Gaussian
    quaternion in 3-D (uniform on SO(3)). Draws from ``generator`` (the global RNG if None).
    """
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim}")
    dtype = dtype or torch.get_default_dtype()
    if isinstance(workspace, (tuple, list)) and len(workspace) == 2:
        low = torch.as_tensor(workspace[0], dtype=dtype).expand(dim)
        high = torch.as_tensor(workspace[1], dtype=dtype).expand(dim)
    else:
        w = torch.as_tensor(workspace, dtype=dtype)
        if w.ndim > 1 or (w.ndim == 1 and w.shape[0] != dim):
            raise ValueError(f"workspace must be a half-width (scalar or [{dim}]) or a (low, high) pair")
        low, high = (-w).expand(dim), w.expand(dim)
    if (high < low).any():
        raise ValueError("workspace high must be >= low")
    position = low + (high - low) * torch.rand(dim, generator=generator, dtype=dtype)
    if dim == 2:
        theta = (2 * torch.rand((), generator=generator, dtype=dtype) - 1) * math.pi
        return Frame(position, rotation_2d(theta))
    q = torch.randn(4, generator=generator, dtype=dtype)
    q = q / torch.linalg.vector_norm(q)
    w_, x, y, z = q.unbind()
    R = torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w_), 2 * (x * z + y * w_)]),
            torch.stack([2 * (x * y + z * w_), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w_)]),
            torch.stack([2 * (x * z - y * w_), 2 * (y * z + x * w_), 1 - 2 * (x * x + y * y)]),
        ]
    )
    return Frame(position, R)
