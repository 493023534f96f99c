"""A DINO vision transformer (Caron et al. 2021, "Emerging Properties in Self-Supervised Vision Transformers") in
plain PyTorch, with the module and parameter names of ``facebookresearch/dino``'s ``vision_transformer.py`` so the
official checkpoints load as they are:

    patch_embed.proj.{weight,bias}  cls_token  pos_embed
    blocks.{i}.norm1  blocks.{i}.attn.qkv  blocks.{i}.attn.proj
    blocks.{i}.norm2  blocks.{i}.mlp.fc1  blocks.{i}.mlp.fc2
    norm.{weight,bias}

:func:`vit_small` is DINO's ViT-S/8 (embed_dim 384, depth 12, 6 heads, MLP ratio 4, qkv bias, LayerNorm eps 1e-6).
Any other size (a tiny random one for tests) is a :class:`VisionTransformer` with other arguments.

Two additions for dense features (Amir et al. 2021, "Deep ViT Features as Dense Visual Descriptors"):
:meth:`VisionTransformer.set_stride` makes the patches overlap, and :meth:`VisionTransformer.facets` returns the
key facet of one block together with the last block's attention in a single pass. Nothing is downloaded: weights
come from a file the user provides (:meth:`VisionTransformer.load_weights`).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Mapping
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

CHECKPOINT_KEYS = ("teacher", "student", "model", "state_dict")
"""Keys a state dict may be nested under, tried in this order (DINO evaluates the teacher)."""


class PatchEmbed(nn.Module):
    """Image ``[B, 3, H, W]`` -> patch tokens ``[B, h*w, D]`` by a ``patch x patch`` convolution.

    With stride s (= patch unless :meth:`VisionTransformer.set_stride` changed it) the token grid is
    h = 1 + (H - patch) // s, w = 1 + (W - patch) // s.
    """

    def __init__(self, patch_size: int, in_chans: int, embed_dim: int):
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(in_chans, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        x = self.proj(x)
        return x.flatten(2).transpose(1, 2), (x.shape[2], x.shape[3])


class Attention(nn.Module):
    """Multi-head self-attention; also returns the attention weights and the key facet."""

    def __init__(self, dim: int, num_heads: int, qkv_bias: bool):
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"embed_dim {dim} is not divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.scale = (dim // num_heads) ** -0.5
        self.qkv = nn.Linear(dim, dim * 3, bias=qkv_bias)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``x [B, N, D]`` -> (output ``[B, N, D]``, attention ``[B, heads, N, N]``, keys ``[B, heads, N, D / heads]``)."""
        b, n, d = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.num_heads, d // self.num_heads).permute(2, 0, 3, 1, 4)
        attn = ((q @ k.transpose(-2, -1)) * self.scale).softmax(dim=-1)
        out = (attn @ v).transpose(1, 2).reshape(b, n, d)
        return self.proj(out), attn, k


class Mlp(nn.Module):
    """fc1 -> GELU -> fc2."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class Block(nn.Module):
    """Pre-norm transformer block: x + attn(norm1(x)), then x + mlp(norm2(x))."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, qkv_bias: bool, eps: float):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=eps)
        self.attn = Attention(dim, num_heads, qkv_bias)
        self.norm2 = nn.LayerNorm(dim, eps=eps)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(tokens, attention, keys) as :meth:`Attention.forward`."""
        y, attn, keys = self.attn(self.norm1(x))
        x = x + y
        return x + self.mlp(self.norm2(x)), attn, keys


class VisionTransformer(nn.Module):
    """DINO's ViT backbone (no classification head); ``forward`` returns the normalised CLS token ``[B, D]``.

    ``img_size`` only sets the size of ``pos_embed`` ((img_size / patch)^2 + 1 positions, as in the checkpoint);
    other image sizes and strides are handled by :meth:`interpolate_pos_encoding`.
    """

    def __init__(
        self,
        img_size: int = 224,
        patch_size: int = 8,
        embed_dim: int = 384,
        depth: int = 12,
        num_heads: int = 6,
        mlp_ratio: float = 4.0,
        qkv_bias: bool = True,
        eps: float = 1e-6,
    ):
        super().__init__()
        if img_size % patch_size:
            raise ValueError(f"img_size {img_size} is not a multiple of patch_size {patch_size}")
        self.patch_embed = PatchEmbed(patch_size, 3, embed_dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, (img_size // patch_size) ** 2 + 1, embed_dim))
        self.blocks = nn.ModuleList(Block(embed_dim, num_heads, mlp_ratio, qkv_bias, eps) for _ in range(depth))
        self.norm = nn.LayerNorm(embed_dim, eps=eps)
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.trunc_normal_(self.cls_token, std=0.02)
        self.apply(_init_weights)

    @property
    def patch_size(self) -> int:
        return self.patch_embed.patch_size

    @property
    def stride(self) -> int:
        return self.patch_embed.proj.stride[0]

    def set_stride(self, stride: int) -> None:
        """Overlapping patches (Amir et al. 2021): the patch convolution moves by ``stride`` pixels, which must divide
        the patch size. The weights are unchanged; the token grid becomes 1 + (H - patch) // stride by
        1 + (W - patch) // stride."""
        if stride < 1 or self.patch_size % stride:
            raise ValueError(f"stride {stride} must be a positive divisor of the patch size {self.patch_size}")
        self.patch_embed.proj.stride = (stride, stride)

    def interpolate_pos_encoding(self, grid: tuple[int, int]) -> torch.Tensor:
        """Positional embeddings ``[1, 1 + h*w, D]`` for an ``h x w`` token grid: the trained square grid resized
        bicubically, as DINO's ``interpolate_pos_encoding`` (with its +0.1 against rounding the output size down)."""
        n = self.pos_embed.shape[1] - 1
        side = math.isqrt(n)
        if grid == (side, side):
            return self.pos_embed
        patch_pos = self.pos_embed[:, 1:].reshape(1, side, side, -1).permute(0, 3, 1, 2)
        scale = ((grid[0] + 0.1) / side, (grid[1] + 0.1) / side)
        patch_pos = F.interpolate(patch_pos, scale_factor=scale, mode="bicubic", align_corners=False)
        patch_pos = patch_pos.permute(0, 2, 3, 1).reshape(1, grid[0] * grid[1], -1)
        return torch.cat([self.pos_embed[:, :1], patch_pos], dim=1)

    def prepare_tokens(self, x: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        """Image ``[B, 3, H, W]`` -> tokens ``[B, 1 + h*w, D]`` (CLS first) with positions added, and the grid (h, w)."""
        if x.shape[-2] < self.patch_size or x.shape[-1] < self.patch_size:
            raise ValueError(f"image {tuple(x.shape[-2:])} is smaller than one {self.patch_size}-pixel patch")
        tokens, grid = self.patch_embed(x)
        tokens = torch.cat([self.cls_token.expand(tokens.shape[0], -1, -1), tokens], dim=1)
        return tokens + self.interpolate_pos_encoding(grid), grid

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x, _ = self.prepare_tokens(x)
        for blk in self.blocks:
            x, _, _ = blk(x)
        return self.norm(x)[:, 0]

    def facets(self, x: torch.Tensor, layer: int) -> tuple[torch.Tensor, torch.Tensor, tuple[int, int]]:
        """The key facet of block ``layer`` (0-based) ``[B, heads, 1 + h*w, D/heads]`` and the last block's attention
        ``[B, heads, 1 + h*w, 1 + h*w]`` (token 0 is CLS), with the grid (h, w), from one forward pass."""
        if not 0 <= layer < len(self.blocks):
            raise ValueError(f"layer {layer} is not a block index of this {len(self.blocks)}-block ViT")
        x, grid = self.prepare_tokens(x)
        keys = attn = None
        for i, blk in enumerate(self.blocks):
            x, attn, k = blk(x)
            if i == layer:
                keys = k
        return keys, attn, grid

    def load_weights(self, path: str | Path) -> None:
        """Load a checkpoint file: a state dict, or one nested under "teacher" / "student" / "model" / "state_dict"
        (DINO's full training checkpoints). "module." prefixes (DistributedDataParallel) are stripped; where keys carry
        a "backbone." prefix only those are kept (DINO's projection "head." is not part of the backbone).

        Loads strictly. Raises ``FileNotFoundError`` for a missing file, ``ValueError`` naming the file for an
        unreadable or corrupt one, and ``ValueError`` listing missing / unexpected keys and shape mismatches.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no checkpoint at {path}")
        try:
            with torch.serialization.safe_globals([argparse.Namespace]):  # DINO checkpoints store their argparse args
                obj = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # truncated, foreign or arbitrary-pickle files raise several types
            raise ValueError(f"{path} is not a readable checkpoint ({type(e).__name__}: {e})") from e
        state = _backbone_state(_find_state_dict(obj, path))
        own = self.state_dict()
        missing = sorted(own.keys() - state.keys())
        unexpected = sorted(state.keys() - own.keys())
        mismatched = [
            f"{k}: checkpoint {list(state[k].shape)} vs model {list(own[k].shape)}"
            for k in sorted(own.keys() & state.keys())
            if state[k].shape != own[k].shape
        ]
        if missing or unexpected or mismatched:
            found = (("missing keys", missing), ("unexpected keys", unexpected), ("shape mismatches", mismatched))
            problems = [f"{label} ({len(items)}): {', '.join(items)}" for label, items in found if items]
            raise ValueError(f"{path} does not fit this ViT; " + "; ".join(problems))
        self.load_state_dict(state, strict=True)


def vit_small(patch_size: int = 8, img_size: int = 224) -> VisionTransformer:
    """DINO's ViT-S (ViT-S/8 by default): embed_dim 384, depth 12, 6 heads, MLP ratio 4, qkv bias, LayerNorm eps 1e-6."""
    return VisionTransformer(img_size=img_size, patch_size=patch_size, embed_dim=384, depth=12, num_heads=6)


def dino_vits8(weights: str | None = None, seed: int = 0) -> VisionTransformer:
    """DINO's ViT-S/8 under its official name (``torch.hub`` ``dino_vits8``): ``weights`` is a checkpoint file the user
    provides (:meth:`VisionTransformer.load_weights`; nothing is downloaded); without one the network is randomly
    initialised from ``seed`` (an untrained control: its descriptors carry no semantics)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = vit_small(patch_size=8)
    if weights is not None:
        model.load_weights(weights)
    return model


def _init_weights(m: nn.Module) -> None:
    """DINO's initialisation: truncated-normal linear weights (std 0.02), zero biases, unit LayerNorms."""
    if isinstance(m, nn.Linear):
        nn.init.trunc_normal_(m.weight, std=0.02)
        nn.init.zeros_(m.bias)
    elif isinstance(m, nn.LayerNorm):
        nn.init.ones_(m.weight)
        nn.init.zeros_(m.bias)


def _is_state_dict(obj: object) -> bool:
    return isinstance(obj, Mapping) and bool(obj) and all(isinstance(v, torch.Tensor) for v in obj.values())


def _find_state_dict(obj: object, path: Path) -> Mapping[str, torch.Tensor]:
    """Descend through :data:`CHECKPOINT_KEYS` until a mapping of names to tensors."""
    while not _is_state_dict(obj):
        key = next((k for k in CHECKPOINT_KEYS if isinstance(obj, Mapping) and isinstance(obj.get(k), Mapping)), None)
        if key is None:
            found = f"keys {sorted(map(str, obj.keys()))}" if isinstance(obj, Mapping) else type(obj).__name__
            raise ValueError(f"{path} holds no state dict of tensors (found {found}; looked under {CHECKPOINT_KEYS})")
        obj = obj[key]
    return obj


def _backbone_state(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    state = {k.removeprefix("module."): v for k, v in state.items()}
    if any(k.startswith("backbone.") for k in state):
        state = {k.removeprefix("backbone."): v for k, v in state.items() if k.startswith("backbone.")}
    return state
