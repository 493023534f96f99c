"""An offline :class:`~kpflow.vision.descriptors.DenseBackbone`: dense SIFT (Lowe 2004) on a regular grid, with a
saliency from the colour distance to the image border's median colour (foreground = unlike the border).

Cells are ``step x step`` tiles from the image's top-left corner (h = H // step by w = W // step; a remainder at
the bottom / right is left out). Each cell's descriptor is OpenCV's SIFT descriptor of an upright keypoint
(angle 0) of diameter ``size`` at the cell centre, computed on the grey image; OpenCV's descriptor covers 4 x 4
spatial bins of 1.5 ``size`` pixels each, i.e. about 6 ``size`` pixels across.

SIFT sees only grey levels, so two objects of one shape but different colours look alike to it. With
``colour_weight`` w > 0 each descriptor is the unit SIFT vector followed by w times the cell's mean RGB in [0, 1]
(so w = 1 lets colour weigh about as much as the gradients).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from kpflow.vision.descriptors import DenseFeatures, check_image, grid_centres, normalise_01


def border_saliency(image: np.ndarray, step: int) -> torch.Tensor:
    """Per-cell saliency ``[H // step, W // step]`` in [0, 1]: the mean Euclidean RGB distance of the cell's pixels to
    the median colour of the image's one-pixel border (a simple background model for an object on a plain backdrop),
    min-max normalised."""
    img = check_image(image).astype(np.float64)
    border = np.concatenate([img[0], img[-1], img[:, 0], img[:, -1]])
    dist = np.linalg.norm(img - np.median(border, axis=0), axis=-1)
    h, w = dist.shape[0] // step, dist.shape[1] // step
    cells = dist[: h * step, : w * step].reshape(h, step, w, step).mean(axis=(1, 3))
    return normalise_01(torch.from_numpy(cells))


class SiftBackbone:
    """Dense SIFT descriptors ``[H // step, W // step, 128]`` (``+ 3`` with colour) with :func:`border_saliency`;
    cell centres (j step + step / 2, i step + step / 2)."""

    def __init__(self, step: int = 8, size: float = 8.0, colour_weight: float = 0.0):
        if step < 1 or size <= 0 or colour_weight < 0:
            raise ValueError(
                f"step must be >= 1, size > 0 and colour_weight >= 0, got step={step}, size={size}, "
                f"colour_weight={colour_weight}"
            )
        self.step, self.size, self.colour_weight = step, float(size), float(colour_weight)
        self._sift = cv2.SIFT_create()

    def __call__(self, image: np.ndarray) -> DenseFeatures:
        image = check_image(image)
        height, width = image.shape[:2]
        grid = (height // self.step, width // self.step)
        if min(grid) == 0:
            raise ValueError(f"image {height}x{width} is smaller than one {self.step}-pixel cell")
        centres = grid_centres(grid, self.step, self.step)
        # OpenCV puts pixel centres at integer coordinates: shift the corner-origin centres by half a pixel
        keypoints = [cv2.KeyPoint(x - 0.5, y - 0.5, self.size, 0.0) for x, y in centres.reshape(-1, 2).tolist()]
        kept, desc = self._sift.compute(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), keypoints)
        if desc is None or len(kept) != len(keypoints):
            described = 0 if desc is None else len(kept)
            raise RuntimeError(f"OpenCV SIFT described {described} of {len(keypoints)} grid points")
        descriptors = torch.from_numpy(desc).reshape(*grid, desc.shape[1])
        if self.colour_weight > 0:
            h, w = grid[0] * self.step, grid[1] * self.step
            rgb = image[:h, :w].reshape(grid[0], self.step, grid[1], self.step, 3).mean(axis=(1, 3)) / 255.0
            unit = descriptors.double() / descriptors.double().norm(dim=-1, keepdim=True).clamp_min(1e-12)
            descriptors = torch.cat([unit, self.colour_weight * torch.from_numpy(rgb)], dim=-1)
        return DenseFeatures(descriptors, border_saliency(image, self.step), centres)
