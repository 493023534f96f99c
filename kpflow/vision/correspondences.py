"""Sparse, well-spread correspondences between two images from any dense backbone, as in Amir et al. 2021 ("Deep
ViT Features as Dense Visual Descriptors", ``find_correspondences``):

1. best buddies: cells that are each other's nearest neighbour by cosine similarity of their descriptors
   (mutual nearest neighbours over all cells), kept where both cells are salient (saliency > threshold);
2. k-means (seeded) over the buddies' concatenated descriptors, normalised to unit length, with ``max_pairs``
   clusters; from each cluster the pair with the largest saliency (image A cell + image B cell) is kept.
   ``spread="pixels"`` clusters the pairs' concatenated pixel positions instead: pairs spread over the images
   rather than over appearance, so a small object that looks like little else still gets a pair.

Pixels are (x, y) in each input image's frame (:mod:`kpflow.vision.descriptors`). Swapping the images swaps the
pairs: buddies are ordered by a key that does not depend on which image comes first (saliency sum, then the sorted
pair of cell indices) before the seeded k-means. Only exact ties, or a k-means decision so close that rounding
(the two halves of each pair vector trade places) tips it, can break the symmetry.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from sklearn.cluster import KMeans

from kpflow.vision.descriptors import DenseBackbone, DenseFeatures

F64 = torch.float64
SPREADS = ("descriptors", "pixels")


@dataclass(frozen=True)
class Correspondences:
    """n matched pairs, most salient first; pixels are (x, y) float64 in each image's own frame."""

    pixels_a: torch.Tensor
    """``[n, 2]`` in image A."""
    pixels_b: torch.Tensor
    """``[n, 2]`` in image B."""
    similarity: torch.Tensor
    """``[n]`` cosine similarity of the two descriptors."""
    saliency_a: torch.Tensor
    """``[n]``"""
    saliency_b: torch.Tensor
    """``[n]``"""

    def __len__(self) -> int:
        return self.pixels_a.shape[0]


def best_buddies(desc_a: torch.Tensor, desc_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mutual nearest neighbours by cosine similarity (Amir et al. 2021) between ``desc_a [Na, C]`` and
    ``desc_b [Nb, C]``: indices ``idx_a``, ``idx_b`` (ascending in ``idx_a``) and their similarities, computed in
    float64. Ties in a nearest neighbour go to the lowest index."""
    sim = F.normalize(desc_a.to(F64), dim=1) @ F.normalize(desc_b.to(F64), dim=1).T
    nn_ab, nn_ba = sim.argmax(dim=1), sim.argmax(dim=0)
    idx_a = torch.nonzero(nn_ba[nn_ab] == torch.arange(len(desc_a), device=sim.device)).squeeze(1)
    idx_b = nn_ab[idx_a]
    return idx_a, idx_b, sim[idx_a, idx_b]


def _flatten(features: DenseFeatures | tuple, name: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(descriptors [N, C], saliency [N], centres [N, 2]) as float64 CPU tensors, checking the shapes agree."""
    if len(features) != 3:
        raise ValueError(f"features of image {name} are (descriptors, saliency, centres), not {len(features)} items")
    # ascontiguousarray: torch cannot wrap numpy arrays with negative strides (flipped images)
    desc, sal, centres = (
        torch.as_tensor(np.ascontiguousarray(t) if isinstance(t, np.ndarray) else t) for t in features
    )
    if desc.ndim != 3 or sal.shape != desc.shape[:2] or centres.shape != (*desc.shape[:2], 2):
        raise ValueError(
            f"features of image {name} must be descriptors [h, w, C], saliency [h, w], centres [h, w, 2]; "
            f"got {list(desc.shape)}, {list(sal.shape)}, {list(centres.shape)}"
        )
    n = desc.shape[0] * desc.shape[1]
    return desc.reshape(n, -1).to("cpu", F64), sal.reshape(n).to("cpu", F64), centres.reshape(n, 2).to("cpu", F64)


def match_features(
    features_a: DenseFeatures | tuple,
    features_b: DenseFeatures | tuple,
    max_pairs: int = 7,
    saliency_threshold: float = 0.2,
    seed: int = 0,
    spread: str = "descriptors",
) -> Correspondences:
    """At most ``max_pairs`` salient, well-spread best-buddy pairs between two backbone outputs (see module doc);
    ``spread`` is ``"descriptors"`` (Amir et al.) or ``"pixels"``."""
    if max_pairs < 1:
        raise ValueError(f"max_pairs must be >= 1, got {max_pairs}")
    if spread not in SPREADS:
        raise ValueError(f"spread must be one of {SPREADS}, got {spread!r}")
    desc_a, sal_a, centres_a = _flatten(features_a, "A")
    desc_b, sal_b, centres_b = _flatten(features_b, "B")
    if desc_a.shape[1] != desc_b.shape[1]:
        raise ValueError(f"descriptor sizes differ: {desc_a.shape[1]} (A) vs {desc_b.shape[1]} (B)")
    idx_a, idx_b, sim = best_buddies(desc_a, desc_b)
    salient = (sal_a[idx_a] > saliency_threshold) & (sal_b[idx_b] > saliency_threshold)
    idx_a, idx_b, sim = idx_a[salient], idx_b[salient], sim[salient]
    score = (sal_a[idx_a] + sal_b[idx_b]).numpy()
    lo, hi = torch.minimum(idx_a, idx_b).numpy(), torch.maximum(idx_a, idx_b).numpy()
    order = torch.from_numpy(np.lexsort((hi, lo, -score)))  # by descending score, then the unordered cell pair
    idx_a, idx_b, sim = idx_a[order], idx_b[order], sim[order]
    if len(idx_a) > max_pairs:
        if spread == "descriptors":
            pairs = torch.cat([desc_a[idx_a], desc_b[idx_b]], dim=1)
            pairs = pairs / pairs.norm(dim=1, keepdim=True).clamp_min(1e-12)
        else:
            pairs = torch.cat([centres_a[idx_a], centres_b[idx_b]], dim=1)
        labels = KMeans(n_clusters=max_pairs, n_init=10, random_state=seed).fit(pairs.numpy()).labels_
        # pairs are sorted by descending score: a cluster's first member is its most salient pair
        first = np.sort(np.unique(labels, return_index=True)[1])
        idx_a, idx_b, sim = idx_a[first], idx_b[first], sim[first]
    return Correspondences(centres_a[idx_a], centres_b[idx_b], sim, sal_a[idx_a], sal_b[idx_b])


def find_correspondences(
    image_a: np.ndarray,
    image_b: np.ndarray,
    backbone: DenseBackbone,
    max_pairs: int = 7,
    saliency_threshold: float = 0.2,
    seed: int = 0,
    spread: str = "descriptors",
) -> Correspondences:
    """:func:`match_features` on ``backbone(image_a)`` and ``backbone(image_b)`` (RGB ``[H, W, 3]`` uint8 images)."""
    return match_features(backbone(image_a), backbone(image_b), max_pairs, saliency_threshold, seed, spread)
