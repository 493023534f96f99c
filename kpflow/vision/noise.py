"""What a real RGB-D camera adds to a rendered frame: depth noise, holes and quantisation, mask errors, a camera
pose known only up to its calibration.

:class:`CameraNoise` turns a clean :class:`~kpflow.vision.cameras.CameraFrame` into the frame a sensor would have
given, seeded by the ``numpy.random.Generator`` it is handed:

* **depth noise**, axial and growing with the square of the distance as an active stereo camera's does (the RMS
  error formula of Intel's RealSense D400 datasheet, ``sigma(z) = z^2 s / (f b)``, subpixel error ``s``, focal
  length ``f`` in pixels, baseline ``b``): ``z' = z + sigma(z) n``, ``n ~ N(0, 1)`` per pixel;
* **holes**: a fraction of pixels return nothing (depth 0), plus every pixel within ``edge_holes`` pixels of a
  depth jump larger than ``edge_jump`` (stereo loses the edges of objects);
* **quantisation** of depth to ``depth_unit`` (the D400's 16-bit depth in 1 mm units);
* **mask errors**: each object's mask eroded or dilated by up to ``mask_px`` pixels (:meth:`CameraNoise.mask`);
* **camera pose error**: the pose the frame reports is the true one turned by ``pose_deg`` degrees about a random
  axis and moved by ``pose_m`` metres in a random direction (a hand-eye calibration's error; the image itself is
  the true camera's).

Defaults: Intel RealSense D435 at 848 x 480 (datasheet: 50 mm baseline, 87 degree horizontal field of view, so
``f = 424 / tan(43.5 deg) = 447`` px; subpixel 0.08: 14 mm RMS at 2 m, inside its 2 % spec), 1 % of pixels dropped, the
edges within 1 pixel of a 2 cm jump dropped, 1 mm depth units, masks off by up to 2 pixels; and the camera's pose off
by 0.25 degree and 2 mm, a good hand-eye calibration's residual (an assumption, not a datasheet's figure: each
0.1 degree moves a point 1.5 m away by 2.6 mm). Occlusion by the robot is not simulated here: the renderer draws the arm and the gripper,
so they hide what they hide. ``CameraNoise.off()`` changes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from .cameras import CameraFrame

D435_FOCAL_PX = 424.0 / np.tan(np.radians(43.5))  # 848 px wide, 87 degrees horizontal field of view


@dataclass(frozen=True)
class CameraNoise:
    """A sensor's errors (module docstring); every value >= 0, 0 turns that error off."""

    subpixel: float = 0.08
    focal_px: float = D435_FOCAL_PX
    baseline_m: float = 0.05
    hole_fraction: float = 0.01
    edge_holes: int = 1
    edge_jump: float = 0.02
    depth_unit: float = 0.001
    mask_px: int = 2
    pose_deg: float = 0.25
    pose_m: float = 0.002

    def __post_init__(self) -> None:
        for name in (
            "subpixel",
            "hole_fraction",
            "edge_holes",
            "edge_jump",
            "depth_unit",
            "mask_px",
            "pose_deg",
            "pose_m",
        ):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"camera noise {name} must be finite and >= 0; got {value!r}")
        if not self.focal_px > 0 or not self.baseline_m > 0:
            raise ValueError(f"focal_px and baseline_m must be > 0; got {self.focal_px} and {self.baseline_m}")
        if self.hole_fraction > 1:
            raise ValueError(f"hole_fraction must be at most 1; got {self.hole_fraction}")

    @classmethod
    def off(cls) -> CameraNoise:
        """No noise at all: frames and masks pass unchanged."""
        return cls(subpixel=0.0, hole_fraction=0.0, edge_holes=0, depth_unit=0.0, mask_px=0, pose_deg=0.0, pose_m=0.0)

    def depth_std(self, z: np.ndarray) -> np.ndarray:
        """The axial RMS error ``z^2 s / (f b)`` (m) at depth ``z`` (m)."""
        return np.square(z) * self.subpixel / (self.focal_px * self.baseline_m)

    def depth(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """A noisy copy of ``depth [H, W]`` (m; holes stay holes and read 0)."""
        d = np.array(depth, np.float64)
        valid = np.isfinite(d) & (d > 0)
        if self.edge_holes:
            filled = np.where(valid, d, 0.0)
            jump = np.maximum(
                ndimage.maximum_filter(filled, 3) - ndimage.minimum_filter(np.where(valid, d, np.inf), 3), 0.0
            )
            valid &= ~ndimage.binary_dilation(jump > self.edge_jump, iterations=int(self.edge_holes))
        d = d + self.depth_std(np.where(valid, d, 0.0)) * rng.standard_normal(d.shape)
        if self.hole_fraction:
            valid &= rng.random(d.shape) >= self.hole_fraction
        if self.depth_unit:
            d = np.round(d / self.depth_unit) * self.depth_unit
        return np.where(valid & (d > 0), d, 0.0)

    def pose(self, cam_to_world: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The camera pose ``[4, 4]`` a calibration off by ``pose_deg`` and ``pose_m`` reports for the true one."""
        axis, direction = (v / np.linalg.norm(v) for v in rng.standard_normal((2, 3)))
        out = np.array(cam_to_world, np.float64)
        out[:3, :3] = Rotation.from_rotvec(np.radians(self.pose_deg) * axis).as_matrix() @ out[:3, :3]
        out[:3, 3] += self.pose_m * direction
        return out

    def mask(self, mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """``mask [H, W]`` eroded or dilated by a whole number of pixels drawn uniformly from ``-mask_px..mask_px``."""
        k = int(rng.integers(-self.mask_px, self.mask_px + 1)) if self.mask_px else 0
        m = np.asarray(mask, bool)
        if k > 0:
            return ndimage.binary_dilation(m, iterations=k)
        return ndimage.binary_erosion(m, iterations=-k) if k < 0 else m

    def frame(
        self, frame: CameraFrame, rng: np.random.Generator, calibration: np.random.Generator | None = None
    ) -> CameraFrame:
        """The frame the sensor gives: noisy depth and the pose its calibration reports, drawn from ``calibration``
        (None: ``rng``; a generator seeded the same way at every capture keeps a camera's error fixed, as one
        calibration does); colour and instance ids as rendered, masks get their error from :meth:`mask` when a
        segmenter reads them."""
        depth = self.depth(frame.depth, rng)
        return replace(
            frame, depth=depth, cam_to_world=self.pose(frame.cam_to_world, rng if calibration is None else calibration)
        )
