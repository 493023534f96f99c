"""One calibrated RGB-D frame, and the world points of a mask in it.

A :class:`CameraFrame` holds what an RGB-D camera gives (colour, metric depth, optionally a per-pixel instance id)
with its calibration: the pinhole intrinsics ``K`` and the camera's pose ``cam_to_world`` in OpenCV's axes (x
right, y down, z along the optical axis; :mod:`kpflow.vision.lifting`). Images are stored top row first, as a
camera delivers them. A pixel ``(row v, column u)`` is lifted at its centre:

    p_cam = depth[v, u] * K^-1 [u + 1/2, v + 1/2, 1]^T,        p_world = cam_to_world p_cam,

so a ``K`` calibrated with pixel centres at integers is passed with ``pixel_offset = 0``
(:func:`~kpflow.vision.lifting.lift_pixels` takes it from :attr:`CameraFrame.pixel_offset`). Depth ``<= 0`` or not
finite is a hole (no return) and lifts to nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .lifting import lift_pixels


@dataclass(frozen=True)
class CameraFrame:
    """An RGB-D frame and its calibration (module docstring).

    Attributes:
        name: the camera's name.
        rgb: ``[H, W, 3]`` uint8.
        depth: ``[H, W]`` metres along the optical axis; ``<= 0`` or NaN where the sensor returned nothing.
        intrinsics: ``K [3, 3]``.
        cam_to_world: ``[4, 4]``, the camera's pose in the world (OpenCV axes).
        segmentation: ``[H, W]`` integer instance ids (-1: none), or None when the camera gives no masks.
        pixel_offset: added to integer pixel indices before lifting (0.5: ``K``'s principal point is in the frame
            whose pixel centres sit at half-integers, as robosuite's and OpenGL's are).
    """

    name: str
    rgb: np.ndarray
    depth: np.ndarray
    intrinsics: np.ndarray
    cam_to_world: np.ndarray
    segmentation: np.ndarray | None = None
    pixel_offset: float = 0.5

    def __post_init__(self) -> None:
        h, w = np.shape(self.depth)[:2] if np.ndim(self.depth) == 2 else (None, None)
        if h is None:
            raise ValueError(f"camera {self.name!r}: depth must be [H, W]; got shape {np.shape(self.depth)}")
        if np.shape(self.rgb) != (h, w, 3):
            raise ValueError(
                f"camera {self.name!r}: rgb must be [H, W, 3] = [{h}, {w}, 3] like the depth; got {np.shape(self.rgb)}"
            )
        if self.segmentation is not None and np.shape(self.segmentation) != (h, w):
            raise ValueError(
                f"camera {self.name!r}: segmentation must be [H, W] = [{h}, {w}]; got {np.shape(self.segmentation)}"
            )
        if np.shape(self.intrinsics) != (3, 3) or np.shape(self.cam_to_world) != (4, 4):
            raise ValueError(
                f"camera {self.name!r}: intrinsics must be 3 x 3 and cam_to_world 4 x 4; got {np.shape(self.intrinsics)} and {np.shape(self.cam_to_world)}"
            )

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return tuple(np.shape(self.depth))

    def valid_depth(self) -> np.ndarray:
        """``[H, W]`` bool: where the depth is a return (finite and > 0)."""
        d = np.asarray(self.depth)
        return np.isfinite(d) & (d > 0)

    def points(self, mask: np.ndarray | None = None) -> np.ndarray:
        """World points ``[N, 3]`` (float64) of the pixels in ``mask [H, W]`` (all when None) that have depth."""
        if mask is not None and np.shape(mask) != self.shape:
            raise ValueError(
                f"camera {self.name!r}: mask must be [H, W] = {list(self.shape)}; got {list(np.shape(mask))}"
            )
        keep = self.valid_depth() if mask is None else self.valid_depth() & np.asarray(mask, bool)
        v, u = np.nonzero(keep)
        if len(v) == 0:
            return np.zeros((0, 3))
        pixels = np.stack([u, v], -1).astype(np.float64)
        depth = np.asarray(self.depth, np.float64)[v, u]
        return lift_pixels(pixels, depth, self.intrinsics, self.cam_to_world, self.pixel_offset).numpy()

    def mask_of(self, ids) -> np.ndarray:
        """``[H, W]`` bool: the pixels whose instance id is one of ``ids``.

        Raises:
            ValueError: the frame has no segmentation.
        """
        if self.segmentation is None:
            raise ValueError(f"camera {self.name!r} gives no segmentation: pass masks from a segmenter instead")
        return np.isin(self.segmentation, np.asarray(list(ids)))
