"""The learned segmenter's loading code (issue 44): Grounding DINO and SAM load from local folders through
``transformers`` (safetensors, nothing downloaded), here tiny randomly initialised models the test saves itself, and
plug into the camera perception behind the ``Segmenter`` protocol."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kpflow.vision.cameras import CameraFrame
from kpflow.vision.keypoint_source import KeypointSource
from kpflow.vision.segmentation import Segmenter

transformers = pytest.importorskip("transformers")

VOCAB = ["[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]", ".", "red", "cube", "green", "can"]


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """Folders of a tiny Grounding DINO (Swin backbone, BERT text encoder, own vocabulary) and a tiny SAM, each with
    its processor, in ``save_pretrained``'s layout."""
    from transformers import (
        BertConfig,
        BertTokenizerFast,
        GroundingDinoConfig,
        GroundingDinoForObjectDetection,
        GroundingDinoImageProcessor,
        GroundingDinoProcessor,
        SamConfig,
        SamImageProcessor,
        SamMaskDecoderConfig,
        SamModel,
        SamProcessor,
        SamPromptEncoderConfig,
        SamVisionConfig,
        SwinConfig,  # fmt: skip
    )

    root = tmp_path_factory.mktemp("segmenter")
    (root / "vocab.txt").write_text("\n".join(VOCAB))
    torch.manual_seed(0)
    swin = SwinConfig(
        embed_dim=8,
        depths=[1, 1, 1, 1],
        num_heads=[1, 1, 1, 1],
        window_size=4,
        out_features=["stage2", "stage3", "stage4"],
    )
    bert = BertConfig(
        vocab_size=len(VOCAB),
        hidden_size=32,
        num_hidden_layers=1,
        num_attention_heads=2,
        intermediate_size=32,
        max_position_embeddings=32,
    )
    detector = GroundingDinoForObjectDetection(GroundingDinoConfig(
        backbone_config=swin, text_config=bert, d_model=32, encoder_layers=1, decoder_layers=2, encoder_attention_heads=2,
        decoder_attention_heads=2, encoder_ffn_dim=32, decoder_ffn_dim=32, num_queries=5, encoder_n_points=1, decoder_n_points=1,
        max_text_len=16))  # fmt: skip
    detector.save_pretrained(root / "dino")
    tokenizer = BertTokenizerFast(vocab_file=str(root / "vocab.txt"))
    GroundingDinoProcessor(
        GroundingDinoImageProcessor(size={"shortest_edge": 64, "longest_edge": 96}), tokenizer
    ).save_pretrained(root / "dino")
    sam = SamModel(SamConfig(
        vision_config=SamVisionConfig(hidden_size=16, num_hidden_layers=1, num_attention_heads=2, mlp_dim=16, output_channels=16,
                                      image_size=64, patch_size=16, global_attn_indexes=[0], window_size=0, num_pos_feats=8),
        prompt_encoder_config=SamPromptEncoderConfig(hidden_size=16, image_size=64, patch_size=16, mask_input_channels=4),
        mask_decoder_config=SamMaskDecoderConfig(hidden_size=16, num_hidden_layers=1, num_attention_heads=2, mlp_dim=16, iou_head_hidden_dim=16)))  # fmt: skip
    sam.save_pretrained(root / "sam")
    SamProcessor(SamImageProcessor(size={"longest_edge": 64}, pad_size={"height": 64, "width": 64})).save_pretrained(
        root / "sam"
    )
    return root / "dino", root / "sam"


def frame() -> CameraFrame:
    rgb = np.zeros((60, 80, 3), np.uint8)
    rgb[20:40, 30:50] = (200, 30, 30)  # a red square
    k = np.array([[80.0, 0, 40], [0, 80.0, 30], [0, 0, 1]])
    return CameraFrame("front", rgb, np.full((60, 80), 1.0), k, np.eye(4))


def test_the_segmenter_loads_local_weights_and_masks_each_name(checkpoints):
    from kpflow.vision.grounded_sam import GroundedSAM

    dino, sam = checkpoints
    segmenter = GroundedSAM(dino, sam, prompts={"cube": "Red cube"}, box_threshold=0.0, text_threshold=0.0)
    assert isinstance(segmenter, Segmenter) and not segmenter.detector.training
    assert segmenter.prompt("cube") == "red cube." and segmenter.prompt("green_can") == "green can."
    box, score = segmenter.box(frame().rgb, "cube")
    assert box.shape == (4,) and 0 <= score <= 1 and box[0] <= box[2] and box[1] <= box[3]
    masks = segmenter.masks(frame(), ["cube", "can"])
    assert [m.shape for m in masks] == [(60, 80)] * 2 and all(m.dtype == bool for m in masks)
    np.testing.assert_array_equal(masks[0], segmenter.masks(frame(), ["cube"])[0])  # deterministic
    strict = GroundedSAM(dino, sam, box_threshold=1.0, text_threshold=1.0)  # nothing passes: empty masks, not seen
    assert strict.box(frame().rgb, "cube") is None and not strict.masks(frame(), ["cube"])[0].any()
    assert KeypointSource("camera", segmenter=segmenter).segmenter is segmenter


def test_the_segmenter_names_what_is_missing_or_wrong(tmp_path, checkpoints):
    from kpflow.vision.grounded_sam import GroundedSAM

    dino, sam = checkpoints
    with pytest.raises(FileNotFoundError, match="no Grounding DINO checkpoint at .*nothing is downloaded"):
        GroundedSAM(tmp_path / "missing", sam)
    with pytest.raises(FileNotFoundError, match="no SAM checkpoint"):
        GroundedSAM(dino, tmp_path)
    with pytest.raises(ValueError, match="thresholds must lie in"):
        GroundedSAM(dino, sam, box_threshold=1.5)
    with pytest.raises(TypeError, match="segmenter must have masks"):
        KeypointSource("camera", segmenter=object())


def test_keypoint_sources_are_checked():
    assert KeypointSource().kind == "sim" and not KeypointSource().camera
    source = KeypointSource("camera", cameras=["frontview"], noise={"mask_px": 0})
    assert (
        source.camera
        and source.cameras == ("frontview",)
        and source.noise.mask_px == 0
        and source.noise.pose_deg == 0.25
    )
    with pytest.raises(ValueError, match="keypoints must come from one of \\['sim', 'camera'\\]"):
        KeypointSource("lidar")
    with pytest.raises(ValueError, match="cameras must be a non-empty list"):
        KeypointSource("camera", cameras="frontview")
    with pytest.raises(ValueError, match="at least 16 x 16"):
        KeypointSource("camera", height=8)
