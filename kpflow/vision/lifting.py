"""Pixels + depth -> 3-D world points and back, with a pinhole camera.

Conventions:

- Camera axes are OpenCV's: x right, y down, z forward (along the optical axis).
- ``depth`` is metric distance along the optical axis (the camera-frame z), not along the ray.
- ``K`` is the 3 x 3 intrinsic matrix (last row [0, 0, 1]; any skew is honoured) and ``cam_to_world`` the 4 x 4
  pose of the camera in the world (p_world = R p_cam + t).
- Lifting: p_cam = z K^-1 [u, v, 1]^T, p_world = cam_to_world p_cam, with (u, v) = pixel + ``pixel_offset``.

Pixels are (x, y) in the frame of :mod:`kpflow.vision.descriptors` (origin at the image's top-left corner, pixel
(row v, column u) centred at (u + 0.5, v + 0.5)), which is the frame of a ``K`` whose principal point is
(W / 2, H / 2) for a centred optical axis, so the default ``pixel_offset=0`` is right for the backbones' cell
centres. Pass ``pixel_offset=0.5`` to lift integer pixel indices (u, v) with such a ``K``, and ``-0.5`` to use
corner-frame pixels with a ``K`` calibrated in OpenCV's frame (pixel centres at integers, principal point near
((W - 1) / 2, (H - 1) / 2)). :func:`project_points` subtracts the same offset, so the two are exact inverses.
"""

from __future__ import annotations

import numpy as np
import torch

F64 = torch.float64


def _f64(x: torch.Tensor | np.ndarray, name: str, last: tuple[int, ...]) -> torch.Tensor:
    t = torch.as_tensor(x, dtype=F64)
    if t.ndim < len(last) or tuple(t.shape[-len(last) :]) != last:
        raise ValueError(f"{name} must have shape [..., {', '.join(map(str, last))}], got {list(t.shape)}")
    return t


def _camera(intrinsics: torch.Tensor | np.ndarray, cam_to_world: torch.Tensor | np.ndarray) -> tuple[torch.Tensor, ...]:
    k = _f64(intrinsics, "intrinsics", (3, 3))
    pose = _f64(cam_to_world, "cam_to_world", (4, 4))
    if k.ndim != 2 or pose.ndim != 2:
        raise ValueError("intrinsics must be one 3 x 3 matrix and cam_to_world one 4 x 4 matrix")
    return k, pose


def lift_pixels(
    pixels: torch.Tensor | np.ndarray,
    depth: torch.Tensor | np.ndarray,
    intrinsics: torch.Tensor | np.ndarray,
    cam_to_world: torch.Tensor | np.ndarray,
    pixel_offset: float = 0.0,
) -> torch.Tensor:
    """World points ``[..., 3]`` (float64) of ``pixels [..., 2]`` (x, y) at ``depth [...]`` (> 0, finite)."""
    k, pose = _camera(intrinsics, cam_to_world)
    uv = _f64(pixels, "pixels", (2,)) + pixel_offset
    z = torch.as_tensor(depth, dtype=F64).expand(uv.shape[:-1])
    if not torch.isfinite(z).all() or (z <= 0).any():
        raise ValueError(f"depth must be finite and > 0; {int((~torch.isfinite(z) | (z <= 0)).sum())} values are not")
    rays = torch.cat([uv, torch.ones_like(uv[..., :1])], dim=-1) @ torch.linalg.inv(k).T
    p_cam = z[..., None] * rays / rays[..., 2:]
    return p_cam @ pose[:3, :3].T + pose[:3, 3]


def project_points(
    points: torch.Tensor | np.ndarray,
    intrinsics: torch.Tensor | np.ndarray,
    cam_to_world: torch.Tensor | np.ndarray,
    pixel_offset: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels ``[..., 2]`` (x, y) and depths ``[...]`` of world ``points [..., 3]``; the inverse of
    :func:`lift_pixels`. Points with depth <= 0 are behind the camera and their pixels meaningless: check the depth."""
    k, pose = _camera(intrinsics, cam_to_world)
    world_to_cam = torch.linalg.inv(pose)
    p_cam = _f64(points, "points", (3,)) @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    uvw = p_cam @ k.T
    return uvw[..., :2] / uvw[..., 2:] - pixel_offset, p_cam[..., 2]


def sample_depth(depth_map: torch.Tensor | np.ndarray, pixels: torch.Tensor | np.ndarray) -> torch.Tensor:
    """Depth ``[...]`` of the pixel containing each (x, y) of ``pixels [..., 2]`` in a ``[H, W]`` depth map (row
    floor(y), column floor(x): no interpolation, so no depth is mixed across an object's edge); ``ValueError`` for
    pixels outside the map. A point on a pixel corner (the centre of an even-sized cell) takes the depth of the
    pixel to its lower right, whose centre is half a pixel away."""
    depth = torch.as_tensor(depth_map, dtype=F64)
    xy = _f64(pixels, "pixels", (2,))
    if depth.ndim != 2:
        raise ValueError(f"depth_map must be [H, W], got {list(depth.shape)}")
    col, row = xy.floor().long().unbind(-1)
    outside = (col < 0) | (row < 0) | (col >= depth.shape[1]) | (row >= depth.shape[0])
    if outside.any():
        raise ValueError(f"{int(outside.sum())} pixels lie outside the {depth.shape[0]}x{depth.shape[1]} depth map")
    return depth[row, col]
