"""Rotation helpers: nearest rotation (polar factor), quaternion conversions (x, y, z, w order, as scipy and
robosuite use), planar rotations, roll-pitch-yaw, the SO(3) exponential and logarithm, and the 6-D representation."""

from __future__ import annotations

import numpy as np
import torch


def nearest_rotation(m: torch.Tensor) -> torch.Tensor:
    """The rotation closest to ``m [..., D, D]`` in Frobenius norm: the orthogonal polar factor U V^T of
    m = U S V^T, with the last singular direction flipped when det(U V^T) < 0 (so det = +1)."""
    u, _, vh = torch.linalg.svd(m)
    det = torch.linalg.det(u @ vh)
    flip = torch.ones_like(m[..., 0, :])
    flip[..., -1] = torch.where(det < 0, -1.0, 1.0).to(m.dtype)
    return (u * flip[..., None, :]) @ vh


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions ``[..., 4]`` (x, y, z, w) to rotation matrices ``[..., 3, 3]``."""
    q = q / q.norm(dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - z * w),
            2 * (x * z + y * w),
            2 * (x * y + z * w),
            1 - 2 * (x * x + z * z),
            2 * (y * z - x * w),
            2 * (x * z - y * w),
            2 * (y * z + x * w),
            1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat(r: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[..., 3, 3]`` to unit quaternions ``[..., 4]`` (x, y, z, w), w >= 0.

    Shepperd's method: take the largest of 4 candidate denominators for numerical stability.
    """
    m = r
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = torch.stack(
        [
            torch.stack(
                [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1], 1 + tr], -1
            ),
            torch.stack(
                [
                    1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 2, 1] - m[..., 1, 2],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[..., 0, 1] + m[..., 1, 0],
                    1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
                    m[..., 1, 2] + m[..., 2, 1],
                    m[..., 0, 2] - m[..., 2, 0],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
                    m[..., 1, 0] - m[..., 0, 1],
                ],
                -1,
            ),
        ],
        -2,
    )  # [..., 4 candidates, 4]
    diag = torch.stack(
        [
            1 + tr,
            1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
        ],
        -1,
    )
    best = diag.argmax(-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., 3:4] < 0, -q, q)


def float_dtype(*xs, dtype: torch.dtype | None = None) -> torch.dtype:
    """``dtype`` if given, else the promoted dtype of the floating tensors among ``xs``, else the default."""
    if dtype is not None:
        return dtype
    out = None
    for x in xs:
        if x is None or isinstance(x, (bool, int, float)):
            continue
        x = torch.as_tensor(x)  # numpy arrays keep their float64 / float32
        if x.is_floating_point():
            out = x.dtype if out is None else torch.promote_types(out, x.dtype)
    return out if out is not None else torch.get_default_dtype()


def _skew(w: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix ``[w]_x`` of ``w`` [..., 3] (so that ``[w]_x v = w x v``)."""
    z = torch.zeros_like(w[..., 0])
    return torch.stack(
        [
            torch.stack([z, -w[..., 2], w[..., 1]], dim=-1),
            torch.stack([w[..., 2], z, -w[..., 0]], dim=-1),
            torch.stack([-w[..., 1], w[..., 0], z], dim=-1),
        ],
        dim=-2,
    )


def rotation_2d(theta, dtype: torch.dtype | None = None) -> torch.Tensor:
    """Planar rotation ``[[cos t, -sin t], [sin t, cos t]]`` for ``theta`` [...] -> [..., 2, 2]."""
    theta = torch.as_tensor(theta, dtype=float_dtype(theta, dtype=dtype))
    c, s = torch.cos(theta), torch.sin(theta)
    return torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)


def euler_to_matrix(rpy, dtype: torch.dtype | None = None) -> torch.Tensor:
    """Rotation from roll-pitch-yaw ``rpy`` [..., 3]: ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    (Fixed-axis X, then Y, then Z -- the ROS / URDF convention.)
    """
    rpy = torch.as_tensor(rpy, dtype=float_dtype(rpy, dtype=dtype))
    if rpy.shape[-1:] != (3,):
        raise ValueError(f"rpy must have shape [..., 3], got {tuple(rpy.shape)}")
    r, p, y = rpy.unbind(-1)
    e = torch.eye(3, dtype=rpy.dtype)
    return so3_exp(y[..., None] * e[2]) @ so3_exp(p[..., None] * e[1]) @ so3_exp(r[..., None] * e[0])


def so3_exp(w) -> torch.Tensor:
    """Rodrigues' formula: rotation vector ``w`` [..., 3] (axis * angle) -> rotation [..., 3, 3].

    ``exp([w]_x) = I + sin(t) K + (1 - cos(t)) K^2`` with ``t = |w|`` and ``K = [w / t]_x``
    (``I`` when ``t = 0``).
    """
    w = torch.as_tensor(w, dtype=float_dtype(w))
    t = torch.linalg.vector_norm(w, dim=-1)[..., None, None]
    K = _skew(w / torch.where(t[..., 0] > 0, t[..., 0], 1.0))
    eye = torch.eye(3, dtype=w.dtype).expand(K.shape)
    return eye + torch.sin(t) * K + (1.0 - torch.cos(t)) * (K @ K)


def so3_log(R) -> torch.Tensor:
    """Rotation vector (axis * angle, angle in [0, pi]) of a single rotation ``R`` [3, 3].

    ``angle = atan2(|v|, (trace R - 1) / 2)`` with ``v = vee(R - R^T) / 2 = sin(angle) axis``.
    Near ``pi`` the axis is read from the symmetric part ``(R + R^T)/2 - cos(angle) I =
    (1 - cos(angle)) axis axis^T`` (sign fixed by ``v``).
    """
    R = torch.as_tensor(R, dtype=float_dtype(R))
    if R.shape != (3, 3):
        raise ValueError(f"so3_log takes one rotation [3, 3], got {tuple(R.shape)}")
    v = 0.5 * torch.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = torch.linalg.vector_norm(v)
    c = (0.5 * (torch.trace(R) - 1.0)).clamp(-1.0, 1.0)
    angle = torch.atan2(s, c)
    if angle < 1e-12:
        return v  # first order: axis * angle ~ v
    if c > -0.9:  # sin(angle) comfortably away from 0
        return v * (angle / s)
    B = 0.5 * (R + R.T) - c * torch.eye(3, dtype=R.dtype)
    col = B[:, torch.argmax(B.diagonal())]
    axis = col / torch.linalg.vector_norm(col)
    if torch.dot(axis, v) < 0:
        axis = -axis
    return axis * angle


def matrix_to_rot6d(r) -> np.ndarray:
    """The continuous 6-D rotation representation of Zhou et al. (2019): the first two columns of ``R [..., 3, 3]``,
    ``[..., 6]`` (column 1, then column 2)."""
    r = np.asarray(r, float)
    return r[..., :, :2].swapaxes(-1, -2).reshape(*r.shape[:-2], 6)


def rot6d_to_matrix(x) -> np.ndarray:
    """The rotation ``[..., 3, 3]`` of a 6-D representation ``[..., 6]`` (Zhou et al. 2019, Eq. 15-16): Gram-Schmidt,
    ``b1 = a1/|a1|``, ``b2 = (a2 - (b1.a2) b1)/|.|``, ``b3 = b1 x b2``."""
    x = np.asarray(x, float)
    a1, a2 = x[..., :3], x[..., 3:]
    b1 = a1 / np.linalg.norm(a1, axis=-1, keepdims=True)
    b2 = a2 - (b1 * a2).sum(-1, keepdims=True) * b1
    b2 = b2 / np.linalg.norm(b2, axis=-1, keepdims=True)
    return np.stack([b1, b2, np.cross(b1, b2)], axis=-1)
