"""Semantic correspondences between two images, and their lifting to 3-D.

- :mod:`kpflow.vision.vit`: DINO's ViT (Caron et al. 2021) with the official checkpoint names (:func:`dino_vits8`).
- :mod:`kpflow.vision.descriptors`: dense key-facet descriptors with log-binning and CLS-attention saliency
  (Amir et al. 2021), and the :class:`DenseBackbone` interface.
- :mod:`kpflow.vision.sift`: an offline dense-SIFT backbone.
- :mod:`kpflow.vision.correspondences`: salient, well-spread best-buddy pairs (Amir et al. 2021).
- :mod:`kpflow.vision.lifting`: pixels + depth <-> 3-D world points with a pinhole camera.
- :mod:`kpflow.vision.consistency`: dropping lifted pairs that break rigidity.

Pixels are (x, y) with the origin at the image's top-left corner and pixel centres at (u + 0.5, v + 0.5).
"""

from kpflow.vision.consistency import rigidly_consistent
from kpflow.vision.correspondences import Correspondences, best_buddies, find_correspondences, match_features
from kpflow.vision.descriptors import (
    DenseBackbone,
    DenseFeatures,
    ViTBackbone,
    cls_saliency,
    dino_backbone,
    grid_centres,
    log_bin,
    vit_descriptors,
)
from kpflow.vision.lifting import lift_pixels, project_points, sample_depth
from kpflow.vision.sift import SiftBackbone, border_saliency
from kpflow.vision.vit import VisionTransformer, dino_vits8, vit_small

__all__ = [
    "Correspondences",
    "DenseBackbone",
    "DenseFeatures",
    "SiftBackbone",
    "ViTBackbone",
    "VisionTransformer",
    "best_buddies",
    "border_saliency",
    "cls_saliency",
    "dino_backbone",
    "dino_vits8",
    "find_correspondences",
    "grid_centres",
    "lift_pixels",
    "log_bin",
    "match_features",
    "project_points",
    "rigidly_consistent",
    "sample_depth",
    "vit_descriptors",
    "vit_small",
]
