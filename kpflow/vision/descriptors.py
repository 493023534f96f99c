"""Dense descriptors and saliency from a ViT, after Amir et al. 2021 ("Deep ViT Features as Dense Visual
Descriptors", the ``dino-vit-features`` extractor), and the interface every backbone of :mod:`kpflow.vision` meets.

A backbone (:class:`DenseBackbone`) maps an RGB image to a grid of cells: descriptors ``[h, w, C]``, a saliency in
[0, 1] ``[h, w]`` and the pixel centre of each cell ``[h, w, 2]``.

Pixel coordinates throughout :mod:`kpflow.vision` are (x, y) = (column, row) in the continuous image frame whose
origin is the top-left corner of the image: pixel (row v, column u) covers [u, u + 1) x [v, v + 1) and has its
centre at (u + 0.5, v + 0.5). This is the frame of an intrinsic matrix whose principal point is (W / 2, H / 2) for
a centred optical axis (see :mod:`kpflow.vision.lifting`).

For a ViT with patch p and stride s, cell (i, j) is the patch whose top-left pixel is (i s, j s); the grid is
h = 1 + (H - p) // s by w = 1 + (W - p) // s and the cell centre is (j s + p / 2, i s + p / 2).
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np
import torch
import torch.nn.functional as F

from kpflow.vision.vit import VisionTransformer, dino_vits8

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class DenseFeatures(NamedTuple):
    """A backbone's output for one image (torch tensors or numpy arrays)."""

    descriptors: torch.Tensor | np.ndarray
    """``[h, w, C]`` one descriptor per cell."""
    saliency: torch.Tensor | np.ndarray
    """``[h, w]`` in [0, 1], high on the foreground."""
    centres: torch.Tensor | np.ndarray
    """``[h, w, 2]`` the (x, y) pixel centre of each cell in the input image's frame."""


class DenseBackbone(Protocol):
    """Anything mapping an RGB image ``[H, W, 3]`` uint8 to (descriptors, saliency, centres): :class:`DenseFeatures`."""

    def __call__(self, image: np.ndarray) -> DenseFeatures | tuple: ...


def check_image(image: np.ndarray) -> np.ndarray:
    """``image`` as a C-contiguous array if it is an ``[H, W, 3]`` uint8 numpy array (a flipped view is copied),
    else ``ValueError``."""
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        desc = f"{type(image).__name__} {getattr(image, 'dtype', '')} {getattr(image, 'shape', '')}"
        raise ValueError(f"expected an [H, W, 3] uint8 RGB numpy image, got {desc}")
    return np.ascontiguousarray(image)


def grid_centres(grid: tuple[int, int], window: float, stride: float) -> torch.Tensor:
    """(x, y) centres ``[h, w, 2]`` (float64) of a grid of ``window``-pixel cells placed every ``stride`` pixels from
    the image's top-left corner: cell (i, j) is centred at (j stride + window / 2, i stride + window / 2)."""
    rows = torch.arange(grid[0], dtype=torch.float64) * stride + window / 2
    cols = torch.arange(grid[1], dtype=torch.float64) * stride + window / 2
    y, x = torch.meshgrid(rows, cols, indexing="ij")
    return torch.stack([x, y], dim=-1)


def normalise_01(x: torch.Tensor) -> torch.Tensor:
    """Min-max scaling to [0, 1]; a constant map becomes all zeros."""
    lo, hi = x.min(), x.max()
    return (x - lo) / (hi - lo) if hi > lo else torch.zeros_like(x)


def log_bin(features: torch.Tensor, hierarchy: int = 2) -> torch.Tensor:
    """Log-binned descriptors (Amir et al. 2021, ``ViTExtractor._log_bin``): ``[B, C, h, w]`` ->
    ``[B, C (1 + 8 hierarchy), h, w]``.

    Level k = 0 .. hierarchy - 1 average-pools 3^k x 3^k neighbourhoods and samples them at the 3 x 3 offsets
    {-3^k, 0, 3^k}^2 around each cell (the centre only once, at level 0), so a descriptor sees ever coarser context
    further away. Offsets past the border take the nearest cell (replicate padding, as the extractor does).
    ``hierarchy=0`` returns the features unchanged. Bins are stacked bin-major along the channels, as in the extractor.
    """
    if hierarchy < 0:
        raise ValueError(f"hierarchy must be >= 0, got {hierarchy}")
    if hierarchy == 0:
        return features
    h, w = features.shape[-2:]
    rows, cols = torch.arange(h, device=features.device), torch.arange(w, device=features.device)
    bins = []
    for k in range(hierarchy):
        size = 3**k
        pooled = F.avg_pool2d(features, size, stride=1, padding=size // 2, count_include_pad=False)
        for di in (-size, 0, size):
            for dj in (-size, 0, size):
                if k > 0 and di == dj == 0:
                    continue
                r, c = (rows + di).clamp(0, h - 1), (cols + dj).clamp(0, w - 1)
                bins.append(pooled[:, :, r][:, :, :, c])
    return torch.cat(bins, dim=1)


def cls_saliency(attn: torch.Tensor, grid: tuple[int, int], heads: tuple[int, ...] | None = None) -> torch.Tensor:
    """Saliency ``[B, h, w]`` in [0, 1] from attention weights ``[B, heads, 1 + h*w, 1 + h*w]`` (token 0 is CLS): the
    CLS -> patch attention averaged over ``heads`` (all by default; Amir et al. 2021 use heads (0, 2, 4, 5) of DINO
    ViT-S/8's last layer), min-max normalised per image."""
    sel = attn if heads is None else attn[:, list(heads)]
    cls_to_patch = sel[:, :, 0, 1:].mean(dim=1).reshape(-1, *grid)
    return torch.stack([normalise_01(s) for s in cls_to_patch])


def vit_descriptors(
    model: VisionTransformer,
    images: torch.Tensor,
    layer: int = 9,
    hierarchy: int = 2,
    saliency_heads: tuple[int, ...] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Descriptors ``[B, h, w, C]`` and saliency ``[B, h, w]`` for normalised images ``[B, 3, H, W]``.

    Descriptors are the key facet of block ``layer`` (0-based; 9 is the one Amir et al. 2021 use for
    correspondences with ViT-S/8), heads concatenated per cell (C = embed_dim before binning), then log-binned with
    ``hierarchy`` levels (:func:`log_bin`). Saliency is the last block's CLS attention (:func:`cls_saliency`).
    The grid is h = 1 + (H - patch) // stride, w = 1 + (W - patch) // stride (:meth:`VisionTransformer.set_stride`).
    """
    keys, attn, grid = model.facets(images, layer)
    b, heads, _, d = keys.shape
    # [B, heads, 1 + t, d] -> [B, d * heads, h, w]: channel index = d_index * heads + head, as the extractor flattens
    per_cell = keys[:, :, 1:].permute(0, 3, 1, 2).reshape(b, d * heads, *grid)
    desc = log_bin(per_cell, hierarchy).permute(0, 2, 3, 1)
    return desc, cls_saliency(attn, grid, saliency_heads)


class ViTBackbone:
    """A :class:`DenseBackbone` from a DINO ViT: ImageNet normalisation, optional resize, :func:`vit_descriptors`.

    ``stride`` (a divisor of the patch size, default the patch size) is set on ``model`` itself
    (:meth:`VisionTransformer.set_stride`). ``resize`` is None (keep the image size), an int (the shorter side
    becomes this many pixels, keeping the aspect ratio, as the extractor's ``load_size``) or (H, W). Features are
    computed on the resized image and the cell centres are mapped back to the input image's pixel frame.
    """

    def __init__(
        self,
        model: VisionTransformer,
        layer: int = 9,
        stride: int | None = None,
        hierarchy: int = 2,
        resize: int | tuple[int, int] | None = None,
        saliency_heads: tuple[int, ...] | None = None,
    ):
        if not 0 <= layer < len(model.blocks):
            raise ValueError(f"layer {layer} is not a block index of this {len(model.blocks)}-block ViT")
        self.model = model.eval()
        if stride is not None:
            model.set_stride(stride)
        self.layer, self.hierarchy, self.resize, self.saliency_heads = layer, hierarchy, resize, saliency_heads

    def _input_size(self, height: int, width: int) -> tuple[int, int]:
        if self.resize is None:
            return height, width
        if isinstance(self.resize, int):
            scale = self.resize / min(height, width)
            return max(1, round(height * scale)), max(1, round(width * scale))
        return self.resize

    @torch.no_grad()
    def __call__(self, image: np.ndarray) -> DenseFeatures:
        image = check_image(image)
        height, width = image.shape[:2]
        param = next(self.model.parameters())
        x = torch.from_numpy(image).to(param).permute(2, 0, 1)[None] / 255.0
        size = self._input_size(height, width)
        if size != (height, width):
            x = F.interpolate(x, size=size, mode="bicubic", antialias=True, align_corners=False).clamp(0.0, 1.0)
        mean = torch.tensor(IMAGENET_MEAN).to(x).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD).to(x).view(1, 3, 1, 1)
        desc, sal = vit_descriptors(self.model, (x - mean) / std, self.layer, self.hierarchy, self.saliency_heads)
        centres = grid_centres(desc.shape[1:3], self.model.patch_size, self.model.stride)
        centres = centres * torch.tensor([width / size[1], height / size[0]], dtype=torch.float64)
        return DenseFeatures(desc[0].cpu(), sal[0].cpu(), centres)


def dino_backbone(
    weights: str | None = None,
    seed: int = 0,
    layer: int = 9,
    stride: int | None = None,
    hierarchy: int = 2,
    resize: int | tuple[int, int] | None = 224,
) -> ViTBackbone:
    """A :class:`ViTBackbone` on DINO's ViT-S/8 (:func:`kpflow.vision.vit.dino_vits8`: the user's ``weights`` file,
    or random from ``seed``), with the descriptor settings of Amir et al. (layer 9 keys, log-binning)."""
    return ViTBackbone(dino_vits8(weights, seed), layer=layer, stride=stride, hierarchy=hierarchy, resize=resize)
