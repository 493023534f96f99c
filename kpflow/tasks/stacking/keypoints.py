"""Keypoints of the stacking task, found in the camera images (the paper's Section 3.2).

The image taken before the demonstration and the image of the new scene are matched by a dense backbone
(:func:`kpflow.vision.find_correspondences`: at most ``max_pairs`` (7) salient best-buddy pairs, spread over
appearance or over the image); both pixels of each
pair are lifted to 3-D with their own depth (:func:`kpflow.vision.lift_pixels`). To these the end effector's start
box is added (the arm starts where it started, :func:`kpflow.tasks.arm.keypoints.end_effector_box`).

The simulator says where each source point should have gone (:func:`true_targets`): a point on a block moves with
the block; a point on anything else stays. :func:`oracle_pairs` gives exact pairs on the blocks' top faces, the
upper bound for what correspondences can give.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from kpflow.vision import (
    DenseBackbone,
    find_correspondences,
    lift_pixels,
    project_points,
    rigidly_consistent,
    sample_depth,
)

from .objects import BLOCKS

BACKGROUND = "table"


@dataclass(frozen=True)
class ImagePairs:
    """Corresponding points of the source image and the image now: ``pixels_before``/``pixels_now [n, 2]``, their
    lifted world points ``source``/``target [n, 3]``, the ``labels`` (what each source pixel shows) and ``kept
    [n]`` (the pairs that survived the rigidity check; all of them when none ran)."""

    pixels_before: np.ndarray
    pixels_now: np.ndarray
    source: np.ndarray
    target: np.ndarray
    labels: list[str]
    kept: np.ndarray


@dataclass(frozen=True)
class Matcher:
    """How stacking finds keypoints in images: at most ``max_pairs`` best-buddy pairs with CLS saliency above
    ``saliency_threshold``, spread over ``spread`` (``"descriptors"``: k-means on appearance, Amir et al.;
    ``"pixels"``: over the image) with k-means seeded by ``seed`` (:func:`kpflow.vision.match_features`), then
    dropping the pairs that break rigidity (``consistency``: the arguments of
    :func:`kpflow.vision.rigidly_consistent`; None keeps every pair)."""

    max_pairs: int = 7
    saliency_threshold: float = 0.2
    spread: str = "descriptors"
    consistency: dict | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if self.max_pairs < 1:
            raise ValueError(f"max_pairs must be >= 1, got {self.max_pairs}")
        if self.spread not in ("descriptors", "pixels"):
            raise ValueError(f"spread must be 'descriptors' or 'pixels', got {self.spread!r}")

    def pairs(self, before: dict, now: dict, backbone: DenseBackbone) -> ImagePairs:
        """The lifted pairs between the images ``before`` and ``now``, the inconsistent ones marked as not kept."""
        pairs = image_pairs(before, now, backbone, self.max_pairs, self.saliency_threshold, self.seed, self.spread)
        if self.consistency is not None:
            pairs = replace(pairs, kept=rigidly_consistent(pairs.source, pairs.target, **self.consistency))
        return pairs


def lift(image: dict, pixels: np.ndarray) -> np.ndarray:
    """World points ``[n, 3]`` of ``pixels [n, 2]`` (x, y) in a top-down image (:meth:`render_topdown`'s dict)."""
    pixels = torch.as_tensor(np.asarray(pixels, float).reshape(-1, 2))
    depth = sample_depth(image["depth"], pixels)
    return lift_pixels(pixels, depth, image["intrinsics"], image["camera_to_world"]).numpy()


def labels_at(image: dict, pixels: np.ndarray) -> list[str]:
    """The block (or ``BACKGROUND``) each pixel ``[n, 2]`` of a top-down image shows."""
    out = []
    for x, y in np.asarray(pixels, float).reshape(-1, 2):
        row, col = int(y), int(x)
        out.append(next((name for name, mask in image["masks"].items() if mask[row, col]), BACKGROUND))
    return out


def true_targets(points: np.ndarray, labels: list[str], poses_before: dict, poses_now: dict) -> np.ndarray:
    """Where source ``points [n, 3]`` are now: a point on a block moves rigidly with it (``poses_*``: name ->
    ``(position [3], rotation [3, 3])``), a background point stays."""
    out = np.array(points, float, copy=True)
    for i, name in enumerate(labels):
        if name != BACKGROUND:
            (p0, r0), (p1, r1) = poses_before[name], poses_now[name]
            out[i] = r1 @ (r0.T @ (points[i] - p0)) + p1
    return out


def image_pairs(
    before: dict,
    now: dict,
    backbone: DenseBackbone,
    max_pairs: int = 7,
    saliency_threshold: float = 0.2,
    seed: int = 0,
    spread: str = "descriptors",
) -> dict:
    """Correspondences between two top-down images, lifted (:class:`ImagePairs`, every pair kept)."""
    corr = find_correspondences(before["rgb"], now["rgb"], backbone, max_pairs, saliency_threshold, seed, spread)
    pa, pb = corr.pixels_a.numpy(), corr.pixels_b.numpy()
    return ImagePairs(pa, pb, lift(before, pa), lift(now, pb), labels_at(before, pa), np.ones(len(pa), bool))


def oracle_pairs(before: dict, now: dict, boxes_before: dict, poses_before: dict, poses_now: dict) -> ImagePairs:
    """Exact pairs: the centre and two adjacent inset corners (not in a line with it: a line leaves the turn about it
    free) of each block's top face (``boxes_before``: name -> ``(centre, rotation, half extents)``), carried by the
    true motion; pixels by projection, for the match images."""
    offsets = np.array([[0.0, 0.0, 1.0], [0.6, 0.6, 1.0], [0.6, -0.6, 1.0]])
    source, labels = [], []
    for name in BLOCKS:
        centre, rot, half = boxes_before[name]
        source.append(centre + (offsets * half) @ rot.T)
        labels += [name] * len(offsets)
    source = np.concatenate(source)
    target = true_targets(source, labels, poses_before, poses_now)

    def pixels(image, points):
        return project_points(points, image["intrinsics"], image["camera_to_world"])[0].numpy()

    return ImagePairs(pixels(before, source), pixels(now, target), source, target, labels, np.ones(len(source), bool))
