"""The object's box from a top-down RGB-D image, as the paper does it: segment, lift to 3-D, fit a minimum-area
rectangle to the footprint, take the top from the highest voxel.

The segmentation mask comes from the simulator (it stands in for a detector plus a segmenter).
"""

from __future__ import annotations

import cv2
import numpy as np

from kpflow.tasks.arm.keypoints import box_corners

VOXEL = 0.005  # m: height bins for the top surface


def backproject(depth: np.ndarray, intrinsics: np.ndarray, camera_to_world: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """World points ``[N, 3]`` of the pixels of ``depth [H, W]`` (metric, along the optical axis) where ``mask``.

    Pinhole model: ``p_cam = z K^-1 [u, v, 1]``, then ``p_world = T_cw p_cam`` (OpenCV camera axes).
    """
    depth = np.asarray(depth, float)
    if depth.ndim != 2:
        raise ValueError(f"depth must be [H, W], got shape {depth.shape}")
    rows, cols = np.nonzero(np.ones_like(depth, bool) if mask is None else mask)
    z = depth[rows, cols]
    k = np.asarray(intrinsics, float)
    u, v = cols + 0.5, rows + 0.5  # pixel centres
    cam = np.stack([(u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z], -1)
    t = np.asarray(camera_to_world, float)
    return cam @ t[:3, :3].T + t[:3, 3]


def top_height(points: np.ndarray, voxel: float = VOXEL, min_points: int = 20) -> float:
    """Mean height of the points in the highest height bin of ``voxel`` m that holds at least ``min_points``."""
    z = points[:, 2]
    bins = np.floor(z / voxel).astype(int)
    values, counts = np.unique(bins, return_counts=True)
    full = values[counts >= min(min_points, counts.max())]
    return float(z[bins == full.max()].mean())


def footprint_rectangle(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """OpenCV's minimum-area rectangle of the points' XY: centre ``[2]``, size ``[2]`` (m) and angle (rad)."""
    (cx, cy), (w, h), angle = cv2.minAreaRect(points[:, :2].astype(np.float32))
    return np.array([cx, cy]), np.array([w, h]), float(np.deg2rad(angle))


def canonical_box(centre: np.ndarray, size: np.ndarray, angle: float, reference_yaw: float = 0.0) -> tuple[np.ndarray, np.ndarray, float]:
    """The same rectangle with its first axis the longer one and its yaw the one nearest ``reference_yaw`` (a
    rectangle is unchanged by half turns: yaw in ``(reference - pi/2, reference + pi/2]``), so that boxes of
    different scenes list their corners in corresponding order."""
    size = np.asarray(size, float)
    if size[1] > size[0]:
        size, angle = size[::-1], angle + np.pi / 2
    offset = (angle - reference_yaw + np.pi / 2) % np.pi - np.pi / 2  # in [-pi/2, pi/2)
    if offset <= -np.pi / 2 + 1e-12:
        offset += np.pi
    return np.asarray(centre, float), size, float(reference_yaw + offset)


def object_box(image: dict, table_height: float, reference_yaw: float = 0.0) -> dict:
    """The object's box from :meth:`~kpflow.tasks.packing.env.PackingEnv.render_topdown`'s output.

    Returns ``centre [2]``, ``size [2]``, ``yaw`` (canonical, nearest ``reference_yaw``), ``top`` (m),
    ``corners [8, 3]`` (bottom at ``table_height``) and the object's ``points [N, 3]``.

    Raises:
        ValueError: the mask holds fewer than 20 pixels (the object is not visible).
    """
    mask = np.asarray(image["mask"], bool)
    if mask.sum() < 20:
        raise ValueError(f"the object covers {int(mask.sum())} pixels of the top-down image: too few to fit a box")
    points = backproject(image["depth"], image["intrinsics"], image["camera_to_world"], mask)
    top = top_height(points)
    upper = points[points[:, 2] > table_height + 0.5 * (top - table_height)]  # drop the edge pixels on the table
    centre, size, yaw = canonical_box(*footprint_rectangle(upper if len(upper) >= 20 else points), reference_yaw)
    return {
        "centre": centre,
        "size": size,
        "yaw": yaw,
        "top": top,
        "corners": box_corners(centre, size, yaw, table_height, top),
        "points": points,
    }
