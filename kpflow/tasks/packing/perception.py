"""The object's box from a top-down RGB-D image, as the paper does it: segment, lift to 3-D, fit a minimum-area
rectangle to the footprint, take the top from the highest voxel.

The segmentation mask comes from the simulator (it stands in for a detector plus a segmenter). With
``keypoints=camera`` (:class:`PackingCamera`) the image gets a sensor's errors first
(:class:`~kpflow.vision.noise.CameraNoise`) and the container's pose is perceived too (:func:`container_pose`);
with ``keypoints=sim`` the object's box is the simulator's (:func:`true_object_box`).
"""

from __future__ import annotations

import cv2
import numpy as np

from kpflow.geometry.angles import yaw_of
from kpflow.tasks.arm.keypoints import box_corners
from kpflow.vision.boxes import fit_footprint_box
from kpflow.vision.cameras import CameraFrame
from kpflow.vision.noise import CameraNoise

VOXEL = 0.005  # m: height bins for the top surface


def topdown_frame(image: dict) -> CameraFrame:
    """The top-down image (:meth:`~kpflow.tasks.packing.env.PackingEnv.render_topdown`'s dict) as a
    :class:`~kpflow.vision.cameras.CameraFrame`, whose :meth:`~kpflow.vision.cameras.CameraFrame.points` lift its
    pixels (``p_cam = z K^-1 [u + 0.5, v + 0.5, 1]``, then ``p_world = T_cw p_cam``; holes dropped)."""
    return CameraFrame("topdown", image["rgb"], image["depth"], image["intrinsics"], image["camera_to_world"])


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


def canonical_box(
    centre: np.ndarray, size: np.ndarray, angle: float, reference_yaw: float = 0.0
) -> tuple[np.ndarray, np.ndarray, float]:
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
    frame = topdown_frame(image)
    mask = np.asarray(image["mask"], bool) & frame.valid_depth()  # a hole has no depth to lift
    if mask.sum() < 20:
        raise ValueError(f"the object covers {int(mask.sum())} pixels of the top-down image: too few to fit a box")
    points = frame.points(mask)
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


def true_object_box(env, table_height: float, reference_yaw: float = 0.0) -> dict:
    """The object's box as :func:`object_box` gives it, from the simulator's pose and extent instead of the camera
    (``keypoints=sim``; no ``points``)."""
    centre, rot, half = env.object_box()
    centre_xy, size, yaw = canonical_box(centre[:2], 2 * half[:2], yaw_of(rot), reference_yaw)
    top = float(centre[2] + half[2])
    return {
        "centre": centre_xy,
        "size": size,
        "yaw": yaw,
        "top": top,
        "corners": box_corners(centre_xy, size, yaw, table_height, top),
    }


def container_pose(image: dict, reference_yaw: float | None = None) -> tuple[np.ndarray, float]:
    """The container's volume centre ``[3]`` and yaw from the top-down image's ``container_mask``: the minimum-area
    rectangle of its walls' footprint (:func:`~kpflow.vision.boxes.fit_footprint_box`), half its height below the
    rim (the highest voxels); the yaw the quarter turn of the square container nearest ``reference_yaw`` (None: in
    ``[-pi/4, pi/4)``)."""
    from .scene import CONTAINER_SIZE  # noqa: PLC0415 (scene imports this module's box helpers)

    mask = np.asarray(image["container_mask"], bool)
    if mask.sum() < 20:
        raise ValueError(f"the container covers {int(mask.sum())} pixels of the top-down image: too few to fit a box")
    box = fit_footprint_box(topdown_frame(image).points(mask), voxel=0.004)
    period, ref = np.pi / 2, 0.0 if reference_yaw is None else reference_yaw
    yaw = float(ref + (box.yaw - ref + period / 2) % period - period / 2)
    return np.r_[box.centre, box.top - CONTAINER_SIZE[2] / 2], yaw


class PackingCamera:
    """The top-down camera with a sensor's errors (``keypoints=camera``): ``noise`` (a D435's by default), the
    calibration error drawn once from ``seed``, depth and mask errors from a stream :meth:`reseed` restarts."""

    def __init__(self, noise: CameraNoise | None = None, seed: int = 0) -> None:
        self.noise = CameraNoise() if noise is None else noise
        self.seed = int(seed)
        self.reseed()

    def reseed(self, *keys: int) -> None:
        self.rng = np.random.default_rng([self.seed, *map(int, keys)])

    def image(self, env) -> dict:
        """:meth:`~kpflow.tasks.packing.env.PackingEnv.render_topdown` as the sensor gives it, plus the container's
        pixels (``container_mask``)."""
        image = dict(env.render_topdown())
        image["container_mask"] = self.noise.mask(image["container_mask"], self.rng)
        image["mask"] = self.noise.mask(image["mask"], self.rng)
        image["depth"] = self.noise.depth(image["depth"], self.rng)
        image["camera_to_world"] = self.noise.pose(image["camera_to_world"], np.random.default_rng([self.seed, 1]))
        return image
