"""The correspondence extractor (kpflow.vision): DINO ViT names and loading, dense descriptors (Amir et al. 2021),
best buddies, dense-SIFT and ViT backbones on synthetic images with known answers, and pinhole lifting."""

import argparse

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from kpflow.vision import (
    SiftBackbone,
    VisionTransformer,
    ViTBackbone,
    best_buddies,
    dino_backbone,
    dino_vits8,
    find_correspondences,
    grid_centres,
    lift_pixels,
    log_bin,
    match_features,
    project_points,
    rigidly_consistent,
    sample_depth,
    vit_small,
)

SHIFT = (24, 16)  # (x, y) pixels: a multiple of every stride used below


def tiny_vit(seed: int = 0, embed_dim: int = 24) -> VisionTransformer:
    torch.manual_seed(seed)
    return VisionTransformer(img_size=32, patch_size=8, embed_dim=embed_dim, depth=3, num_heads=2).eval()


def scene(seed: int = 0) -> np.ndarray:
    """A 128 x 160 plain backdrop with a 48 x 56 smoothly textured object in the middle."""
    rng = np.random.default_rng(seed)
    img = np.full((128, 160, 3), (200, 190, 180), np.uint8)
    texture = rng.integers(0, 256, size=(12, 14, 3)).astype(np.uint8)
    img[40:88, 48:104] = cv2.resize(texture, (56, 48), interpolation=cv2.INTER_CUBIC)
    return img


def shifted_views(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Two 96 x 128 crops of :func:`scene`; the object sits SHIFT pixels further right / down in the first."""
    img = scene(seed)
    return img[8:104, 8:136], img[8 + SHIFT[1] : 104 + SHIFT[1], 8 + SHIFT[0] : 136 + SHIFT[0]]


def backbone(name: str):
    return {
        "sift": lambda: SiftBackbone(step=8, size=4),
        "vit-stride8": lambda: ViTBackbone(tiny_vit(), layer=1),
        "vit-stride4": lambda: ViTBackbone(tiny_vit(), layer=1, stride=4),
    }[name]()


# --- ViT ------------------------------------------------------------------------------------------------------------


def test_vit_small_has_the_parameter_names_and_shapes_of_dino_vits8():
    d, hidden = 384, 1536
    expected = {
        "cls_token": [1, 1, d],
        "pos_embed": [1, 785, d],
        "patch_embed.proj.weight": [d, 3, 8, 8],
        "patch_embed.proj.bias": [d],
        "norm.weight": [d],
        "norm.bias": [d],
    }
    for i in range(12):
        expected |= {
            f"blocks.{i}.norm1.weight": [d],
            f"blocks.{i}.norm1.bias": [d],
            f"blocks.{i}.attn.qkv.weight": [3 * d, d],
            f"blocks.{i}.attn.qkv.bias": [3 * d],
            f"blocks.{i}.attn.proj.weight": [d, d],
            f"blocks.{i}.attn.proj.bias": [d],
            f"blocks.{i}.norm2.weight": [d],
            f"blocks.{i}.norm2.bias": [d],
            f"blocks.{i}.mlp.fc1.weight": [hidden, d],
            f"blocks.{i}.mlp.fc1.bias": [hidden],
            f"blocks.{i}.mlp.fc2.weight": [d, hidden],
            f"blocks.{i}.mlp.fc2.bias": [d],
        }
    model = vit_small()
    assert {k: list(v.shape) for k, v in model.state_dict().items()} == expected
    assert sum(p.numel() for p in model.parameters()) == 21_670_272  # DINO's ViT-S/8
    assert all(blk.norm1.eps == 1e-6 and blk.attn.num_heads == 6 for blk in model.blocks)


def test_stride_must_divide_the_patch_and_keeps_the_weights():
    model = tiny_vit()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    model.set_stride(4)
    assert model.patch_embed.proj.stride == (4, 4)
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    with pytest.raises(ValueError, match="divisor"):
        model.set_stride(3)


def test_positional_embedding_interpolation():
    model = tiny_vit()
    assert model.interpolate_pos_encoding((4, 4)) is model.pos_embed  # the trained 4 x 4 grid: as is
    with torch.no_grad():
        model.pos_embed[:, 1:] = torch.arange(24.0)  # the same vector at every position
    pos = model.interpolate_pos_encoding((15, 19))
    assert pos.shape == (1, 1 + 15 * 19, 24)
    torch.testing.assert_close(pos[:, 0], model.pos_embed[:, 0])  # CLS position untouched
    torch.testing.assert_close(pos[0, 1:], torch.arange(24.0).expand(15 * 19, -1))  # bicubic keeps constants


# --- weights ----------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("layout", ["raw", "dino-full", "state_dict"])
def test_load_weights_gives_identical_outputs(tmp_path, layout):
    source, target = tiny_vit(seed=0), tiny_vit(seed=1)
    state = source.state_dict()
    if layout == "dino-full":  # DDP student/teacher with a projection head, as DINO's full checkpoints
        teacher = {f"module.backbone.{k}": v for k, v in state.items()}
        teacher["module.head.last_layer.weight"] = torch.ones(5, 24)  # not part of the backbone: ignored
        state = {"teacher": teacher, "epoch": 3, "args": argparse.Namespace(arch="vit_small", patch_size=8)}
    elif layout == "state_dict":
        state = {"state_dict": {f"module.{k}": v for k, v in state.items()}}
    torch.save(state, tmp_path / "ckpt.pth")
    x = torch.randn(2, 3, 40, 48)
    with torch.no_grad():
        assert not torch.allclose(source(x), target(x))
        target.load_weights(tmp_path / "ckpt.pth")
        torch.testing.assert_close(target(x), source(x), rtol=0, atol=0)


def test_load_weights_explains_what_is_wrong(tmp_path):
    model = tiny_vit()
    torch.save(model.state_dict(), tmp_path / "whole.pth")
    (tmp_path / "corrupt.pth").write_bytes((tmp_path / "whole.pth").read_bytes()[:2000])  # a truncated download
    with pytest.raises(ValueError, match="corrupt.pth is not a readable checkpoint"):
        model.load_weights(tmp_path / "corrupt.pth")
    with pytest.raises(FileNotFoundError):
        model.load_weights(tmp_path / "missing.pth")

    torch.save(tiny_vit(embed_dim=32).state_dict(), tmp_path / "wide.pth")
    with pytest.raises(ValueError, match=r"shape mismatches .*cls_token: checkpoint \[1, 1, 32\] vs model \[1, 1, 24"):
        model.load_weights(tmp_path / "wide.pth")

    state = model.state_dict()
    del state["norm.bias"]
    torch.save(state | {"head.weight": torch.zeros(3)}, tmp_path / "partial.pth")
    with pytest.raises(ValueError, match=r"missing keys \(1\): norm.bias; unexpected keys \(1\): head.weight"):
        model.load_weights(tmp_path / "partial.pth")

    torch.save({"epoch": 3, "optimizer": {"lr": 0.1}}, tmp_path / "no_weights.pth")
    with pytest.raises(ValueError, match="holds no state dict"):
        model.load_weights(tmp_path / "no_weights.pth")


# --- descriptors ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("stride, grid", [(8, (8, 10)), (4, (15, 19))])
def test_vit_descriptor_grid_and_stride(stride, grid):
    """Grid 1 + (H - 8) // stride by 1 + (W - 8) // stride on a 64 x 80 image; cells 8 x 8, centres stride apart."""
    image = np.random.default_rng(0).integers(0, 256, size=(64, 80, 3), dtype=np.uint8)
    desc, sal, centres = ViTBackbone(tiny_vit(), layer=1, stride=stride)(image)
    assert desc.shape == (*grid, 24 * 17)  # embed_dim x (1 + 8 * 2 log-bins)
    assert sal.shape == grid and sal.min() == 0 and sal.max() == 1
    torch.testing.assert_close(centres[0, 0], torch.tensor([4.0, 4.0], dtype=torch.float64))
    torch.testing.assert_close(centres[1, 2] - centres[0, 0], torch.tensor([2.0 * stride, stride], dtype=torch.float64))
    assert ViTBackbone(tiny_vit(), layer=1, stride=stride, hierarchy=0)(image).descriptors.shape == (*grid, 24)


def test_resized_input_reports_centres_in_the_original_frame():
    image = np.random.default_rng(0).integers(0, 256, size=(64, 80, 3), dtype=np.uint8)
    vit = ViTBackbone(tiny_vit(), layer=1, resize=32)
    desc, _, centres = vit(image)  # computed on 32 x 40: a 4 x 5 grid
    assert desc.shape[:2] == (4, 5)
    torch.testing.assert_close(centres[3, 4], torch.tensor([72.0, 56.0], dtype=torch.float64))  # (4 * 8 + 4) * 2
    mirrored = image[:, ::-1]  # a view with a negative stride
    torch.testing.assert_close(vit(mirrored).descriptors, vit(mirrored.copy()).descriptors)


def test_log_bin_matches_the_per_cell_definition():
    """Each cell gets the mean of the 3^k x 3^k window (clipped to the grid) around each of the 3 x 3 offsets
    {-3^k, 0, 3^k}^2, with offsets past the border clamped to the nearest cell."""
    feats = torch.randn(1, 2, 5, 7, dtype=torch.float64)
    binned = log_bin(feats, hierarchy=2)
    assert binned.shape == (1, 2 * 17, 5, 7)
    for y in range(5):
        for x in range(7):
            expected = []
            for k, size in enumerate((1, 3)):
                for i in (y - size, y, y + size):
                    for j in (x - size, x, x + size):
                        if k and (i, j) == (y, x):
                            continue
                        r, c = min(max(i, 0), 4), min(max(j, 0), 6)
                        half = size // 2
                        window = feats[0, :, max(r - half, 0) : r + half + 1, max(c - half, 0) : c + half + 1]
                        expected.append(window.mean(dim=(1, 2)))
            torch.testing.assert_close(binned[0, :, y, x], torch.cat(expected))


def test_sift_backbone_grid_and_border_saliency():
    image = scene()
    desc, sal, centres = SiftBackbone(step=8, size=4)(image)
    assert desc.shape == (16, 20, 128) and sal.shape == (16, 20)
    torch.testing.assert_close(centres[2, 3], torch.tensor([28.0, 20.0], dtype=torch.float64))
    assert sal.max() == 1 and (sal[:4] == 0).all() and (sal[:, :5] == 0).all()  # the plain backdrop
    assert (sal[5:11, 6:13] > 0).all()  # cells inside the object (rows 40..88, columns 48..104)


# --- correspondences --------------------------------------------------------------------------------------------------


def test_best_buddies_are_symmetric():
    bb = SiftBackbone(step=8, size=4)
    fa, fb = bb(scene(0)), bb(scene(1))
    da, db = fa.descriptors.reshape(-1, 128), fb.descriptors.reshape(-1, 128)
    ia, ib, sim = best_buddies(da, db)
    ib2, ia2, sim2 = best_buddies(db, da)
    assert len(ia) > 7
    assert sorted(zip(ia.tolist(), ib.tolist())) == sorted(zip(ia2.tolist(), ib2.tolist()))
    torch.testing.assert_close(sim.sort().values, sim2.sort().values)

    ab, ba = match_features(fa, fb), match_features(fb, fa)
    assert len(ab) == 7  # k-means picked 7 of the salient buddies
    torch.testing.assert_close(ab.pixels_a, ba.pixels_b)
    torch.testing.assert_close(ab.pixels_b, ba.pixels_a)


@pytest.mark.parametrize("name", ["sift", "vit-stride8", "vit-stride4"])
def test_image_matched_to_itself_gives_identity_pairs(name):
    image = np.random.default_rng(3).integers(0, 256, size=(64, 80, 3), dtype=np.uint8)
    features = backbone(name)(image)
    pairs = match_features(features, features)
    assert len(pairs) == 7
    torch.testing.assert_close(pairs.pixels_a, pairs.pixels_b)
    torch.testing.assert_close(pairs.similarity, torch.ones(7, dtype=torch.float64))
    assert len({tuple(p) for p in pairs.pixels_a.tolist()}) == 7  # one pair per cluster
    assert (pairs.saliency_a > 0.2).all() and (pairs.saliency_a[:-1] >= pairs.saliency_a[1:]).all()


@pytest.mark.parametrize("name", ["sift", "vit-stride8", "vit-stride4"])
def test_known_shift_is_recovered(name):
    """The object moves by SHIFT between the crops. The random-weight ViT recovers it as well: the backdrop is
    plain and the object fully visible in both crops, so both hold the same patch tokens and only the (small,
    randomly initialised) positional embeddings differ."""
    view_a, view_b = shifted_views()
    pairs = find_correspondences(view_a, view_b, backbone(name))
    assert len(pairs) == 7
    torch.testing.assert_close(pairs.pixels_a - pairs.pixels_b, torch.tensor(SHIFT, dtype=torch.float64).expand(7, 2))
    assert (pairs.similarity > 0.99).all()


def test_any_callable_backbone_plugs_in():
    """A plain function returning numpy arrays: raw 8 x 8 colour patches as descriptors, uniform saliency."""

    def raw_patches(image):
        h, w = image.shape[0] // 8, image.shape[1] // 8
        cells = image[: h * 8, : w * 8].reshape(h, 8, w, 8, 3).transpose(0, 2, 1, 3, 4).reshape(h, w, -1)
        return cells.astype(np.float32), np.ones((h, w)), grid_centres((h, w), 8, 8).numpy()

    image = np.random.default_rng(4).integers(0, 256, size=(64, 80, 3), dtype=np.uint8)
    rolled = np.roll(image, shift=(SHIFT[1], SHIFT[0]), axis=(0, 1))
    pairs = find_correspondences(rolled, image, raw_patches)
    assert len(pairs) == 7
    # a rolled image wraps around: pixel (x, y) of the image is at ((x + dx) mod W, (y + dy) mod H) in the roll
    expected = (pairs.pixels_b + torch.tensor(SHIFT).double()) % torch.tensor([80.0, 64.0]).double()
    torch.testing.assert_close(pairs.pixels_a, expected)


def test_inconsistent_backbone_output_is_rejected():
    good = (torch.zeros(4, 5, 3), torch.ones(4, 5), torch.zeros(4, 5, 2))
    bad = (torch.zeros(4, 5, 3), torch.ones(5, 4), torch.zeros(4, 5, 2))
    with pytest.raises(ValueError, match="saliency"):
        match_features(good, bad)
    with pytest.raises(ValueError, match="uint8"):
        SiftBackbone()(np.zeros((32, 32, 3), np.float32))


# --- lifting ----------------------------------------------------------------------------------------------------------


def camera(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """640 x 480 intrinsics with the principal point at (W / 2, H / 2), and a random camera-to-world pose."""
    k = torch.tensor([[600.0, 0.0, 320.0], [0.0, 580.0, 240.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = torch.from_numpy(Rotation.random(random_state=seed).as_matrix())
    pose[:3, 3] = torch.tensor([0.4, -0.2, 1.1], dtype=torch.float64)
    return k, pose


@pytest.mark.parametrize("pixel_offset", [0.0, 0.5, -0.5])
def test_lifting_round_trips(pixel_offset):
    k, pose = camera(seed=0)
    rng = np.random.default_rng(0)
    p_cam = np.stack([rng.uniform(-0.5, 0.5, 50), rng.uniform(-0.4, 0.4, 50), rng.uniform(0.3, 3.0, 50)], -1)
    world = torch.from_numpy(p_cam) @ pose[:3, :3].T + pose[:3, 3]
    pixels, depth = project_points(world, k, pose, pixel_offset)
    torch.testing.assert_close(depth, torch.from_numpy(p_cam[:, 2]))  # depth along the optical axis
    assert (lift_pixels(pixels, depth, k, pose, pixel_offset) - world).norm(dim=-1).max() < 1e-3  # well under 1 mm
    # and pixel -> world -> pixel
    pix = torch.from_numpy(rng.uniform([0, 0], [640, 480], (50, 2)))
    again, _ = project_points(lift_pixels(pix, 1.7, k, pose, pixel_offset), k, pose, pixel_offset)
    torch.testing.assert_close(again, pix)


def test_lifting_a_depth_map_of_a_plane_lands_on_the_plane():
    """Render the depth of the world plane z = 0 seen by a tilted camera 1.5 m above it, then lift pixel centres."""
    k, pose = camera(seed=0)
    pose[:3, :3] = torch.from_numpy(Rotation.from_euler("x", 160, degrees=True).as_matrix())  # looking down, tilted
    pose[:3, 3] = torch.tensor([0.1, 0.2, 1.5], dtype=torch.float64)
    v, u = torch.meshgrid(torch.arange(480.0).double(), torch.arange(640.0).double(), indexing="ij")
    rays = torch.stack([u + 0.5, v + 0.5, torch.ones_like(u)], -1) @ torch.linalg.inv(k).T @ pose[:3, :3].T
    depth_map = -pose[2, 3] / rays[..., 2]  # ray direction has camera z = 1, so its length scale is the depth
    assert (depth_map > 0).all()

    centres = grid_centres((60, 80), 1, 8)  # the centre of every 8th pixel: (8 j + 0.5, 8 i + 0.5)
    points = lift_pixels(centres, sample_depth(depth_map, centres), k, pose)
    torch.testing.assert_close(points[..., 2], torch.zeros(60, 80, dtype=torch.float64), rtol=0, atol=1e-9)
    # the same pixels as integer indices (u, v) lift identically with pixel_offset = 0.5
    indices = centres.floor()
    index_depth = depth_map[indices[..., 1].long(), indices[..., 0].long()]
    torch.testing.assert_close(lift_pixels(indices, index_depth, k, pose, pixel_offset=0.5), points)


def test_lifting_rejects_invalid_depth_and_pixels():
    k, pose = camera(seed=0)
    with pytest.raises(ValueError, match="depth must be finite and > 0"):
        lift_pixels(torch.zeros(3, 2), torch.tensor([1.0, 0.0, float("nan")]), k, pose)
    with pytest.raises(ValueError, match="outside"):
        sample_depth(torch.ones(48, 64), torch.tensor([[64.0, 10.0]]))


def test_sift_colour_term_tells_apart_blocks_that_grey_sift_confuses():
    rng = np.random.default_rng(0)
    grey = rng.integers(60, 200, size=(64, 64), dtype=np.uint8)
    yellow = np.stack([grey, grey, (grey * 0.2).astype(np.uint8)], -1)
    blue = np.stack([(grey * 0.2).astype(np.uint8), grey, grey], -1)
    plain, coloured = SiftBackbone(), SiftBackbone(colour_weight=2.0)
    assert (
        np.asarray(plain(yellow).descriptors).shape[-1] == 128
        and np.asarray(coloured(yellow).descriptors).shape[-1] == 131
    )

    def similarity(backbone):  # mean cosine similarity of each cell's descriptor in the two images
        a, b = (torch.as_tensor(np.asarray(backbone(img).descriptors), dtype=torch.float64) for img in (yellow, blue))
        return torch.nn.functional.cosine_similarity(a, b, dim=-1).mean().item()

    assert similarity(coloured) < similarity(plain) - 0.2
    with pytest.raises(ValueError, match="colour_weight"):
        SiftBackbone(colour_weight=-1.0)


def test_dino_vits8_is_seeded_and_loads_user_weights(tmp_path):
    assert isinstance(dino_vits8(seed=0), VisionTransformer)
    a, b, c = dino_backbone(seed=0), dino_backbone(seed=0), dino_backbone(seed=1)
    state = a.model.state_dict()
    assert all(torch.equal(state[k], v) for k, v in b.model.state_dict().items())
    assert not torch.equal(state["cls_token"], c.model.state_dict()["cls_token"])
    path = tmp_path / "dino_deitsmall8_pretrain.pth"
    torch.save(c.model.state_dict(), path)
    loaded = dino_backbone(weights=str(path), seed=0)
    assert all(torch.equal(v, loaded.model.state_dict()[k]) for k, v in c.model.state_dict().items())
    assert loaded.layer == 9 and loaded.resize == 224


def test_pixel_spread_gives_every_part_of_the_image_a_pair():
    """Descriptors that differ only in a few cells: clustering appearance spends the pairs on those few cells, while
    clustering positions puts one pair in each quadrant of the image."""
    rng = np.random.default_rng(5)
    h = w = 10
    desc = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (h, w, 1)) + 1e-3 * rng.standard_normal((h, w, 4))
    desc[0, :3] = rng.standard_normal((3, 4))  # three distinctive cells in the top-left quadrant's first row
    features = (desc, np.ones((h, w)), grid_centres((h, w), 8, 8).numpy())
    quadrant = lambda p: (int(p[0] >= 40), int(p[1] >= 40))  # noqa: E731
    by_pixels = match_features(features, features, max_pairs=4, spread="pixels")
    assert sorted(quadrant(p) for p in by_pixels.pixels_a.tolist()) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    by_descriptors = match_features(features, features, max_pairs=4)
    assert sum(quadrant(p) == (0, 0) for p in by_descriptors.pixels_a.tolist()) >= 3
    torch.testing.assert_close(by_pixels.pixels_a, by_pixels.pixels_b)
    with pytest.raises(ValueError, match="spread"):
        match_features(features, features, spread="space")


def test_rigidity_check_drops_the_pair_that_fits_no_object():
    rng = np.random.default_rng(6)
    block_a = rng.uniform(-0.04, 0.04, size=(4, 3))
    block_b = rng.uniform(-0.04, 0.04, size=(3, 3)) + [0.4, 0.0, 0.0]
    lone = np.array([[0.0, 0.6, 0.0]])
    source = np.concatenate([block_a, block_b, lone])
    turn = Rotation.from_euler("z", 0.6).as_matrix()
    target = np.concatenate([block_a @ turn.T + [0.1, 0.2, 0.0], block_b - [0.0, 0.3, 0.0], lone + 0.5])
    assert rigidly_consistent(source, target).all()  # two blocks moving differently, and a point far from both
    wrong = target.copy()
    wrong[1] = target[5]  # a point of block A matched onto block B
    assert rigidly_consistent(source, wrong).tolist() == [True, False, True, True, True, True, True, True]
    lone_pair = rigidly_consistent(
        np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]]), np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]])
    )
    assert not lone_pair.any()  # two neighbours that disagree: nothing tells which is wrong, so both go
    with pytest.raises(ValueError, match="both be"):
        rigidly_consistent(source, target[:3])
    with pytest.raises(ValueError, match="> 0"):
        rigidly_consistent(source, target, tolerance=0.0)
