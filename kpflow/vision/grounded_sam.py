"""A learned segmenter: an open-vocabulary detector boxes each named object, a promptable mask model segments the
box (Grounding DINO + SAM, the paper's Sec. 3.3), through Hugging Face ``transformers``.

For each name, the detector (``GroundingDinoForObjectDetection``; Liu et al. 2023) reads the frame's RGB with the
name's text prompt (``"red cube."``) and its highest-scoring box above ``box_threshold`` (and ``text_threshold``)
is handed to SAM (``SamModel``; Kirillov et al. 2023) as a box prompt; SAM's mask for it, resized to the frame, is
the object's. A name with no box gets an empty mask (not seen).

Both models load from local folders only (``from_pretrained(path, local_files_only=True)``, safetensors weights,
no remote code): nothing is downloaded and nothing loaded runs code. Point ``detector`` at a folder holding, e.g.,
``IDEA-Research/grounding-dino-tiny`` and ``sam`` at ``facebook/sam-vit-base`` fetched beforehand.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from .cameras import CameraFrame


def _folder(path: str | Path, what: str) -> Path:
    folder = Path(path).expanduser()
    if not (folder / "config.json").is_file():
        raise FileNotFoundError(f"no {what} at {str(folder)!r}: expected a folder with config.json and model.safetensors "
                                "(save_pretrained's layout); nothing is downloaded")  # fmt: skip
    return folder


class GroundedSAM:
    """Masks of named objects from a detector and a mask model (module docstring).

    Args:
        detector: folder of a Grounding DINO checkpoint and its processor.
        sam: folder of a SAM checkpoint and its processor.
        prompts: object name -> the text that describes it (a name without one is its own prompt).
        box_threshold, text_threshold: the detector's score thresholds.
        device: where the models run.
    """

    def __init__(self, detector: str | Path, sam: str | Path, prompts: Mapping[str, str] | None = None, box_threshold: float = 0.35,
                 text_threshold: float = 0.25, device: str = "cpu") -> None:  # fmt: skip
        from transformers import GroundingDinoForObjectDetection, GroundingDinoProcessor, SamModel, SamProcessor

        if not 0 <= box_threshold <= 1 or not 0 <= text_threshold <= 1:
            raise ValueError(f"thresholds must lie in [0, 1]; got box {box_threshold}, text {text_threshold}")
        detector, sam = _folder(detector, "Grounding DINO checkpoint"), _folder(sam, "SAM checkpoint")
        load = {"local_files_only": True}
        self.detector = (
            GroundingDinoForObjectDetection.from_pretrained(detector, use_safetensors=True, **load).to(device).eval()
        )
        self.detector_processor = GroundingDinoProcessor.from_pretrained(detector, **load)
        self.sam = SamModel.from_pretrained(sam, use_safetensors=True, **load).to(device).eval()
        self.sam_processor = SamProcessor.from_pretrained(sam, **load)
        self.prompts = dict(prompts or {})
        self.box_threshold, self.text_threshold, self.device = float(box_threshold), float(text_threshold), device

    def prompt(self, name: str) -> str:
        """The detector's text for ``name``: lower case, ending with a full stop (Grounding DINO's convention)."""
        text = self.prompts.get(name, name.replace("_", " ")).strip().lower()
        return text if text.endswith(".") else text + "."

    @torch.no_grad()
    def box(self, rgb: np.ndarray, name: str) -> tuple[np.ndarray, float] | None:
        """The best box ``[x0, y0, x1, y1]`` (pixels) of ``name`` in ``rgb [H, W, 3]`` and its score; None if none
        passes the thresholds."""
        inputs = self.detector_processor(images=rgb, text=self.prompt(name), return_tensors="pt").to(self.device)
        outputs = self.detector(**inputs)
        found = self.detector_processor.post_process_grounded_object_detection(
            outputs,
            inputs["input_ids"],
            threshold=self.box_threshold,
            text_threshold=self.text_threshold,
            target_sizes=[rgb.shape[:2]],
        )[0]
        if not len(found["scores"]):
            return None
        best = int(torch.argmax(found["scores"]))
        return found["boxes"][best].cpu().numpy(), float(found["scores"][best])

    @torch.no_grad()
    def segment_box(self, rgb: np.ndarray, box: np.ndarray) -> np.ndarray:
        """SAM's mask ``[H, W]`` bool of the object in ``box`` (pixels) of ``rgb``."""
        inputs = self.sam_processor(
            images=rgb, input_boxes=[[np.asarray(box, float).tolist()]], return_tensors="pt"
        ).to(self.device)
        outputs = self.sam(**inputs, multimask_output=False)
        masks = self.sam_processor.image_processor.post_process_masks(outputs.pred_masks.cpu(), inputs["original_sizes"].cpu(),
                                                                      inputs["reshaped_input_sizes"].cpu())  # fmt: skip
        return masks[0][0, 0].numpy().astype(bool)

    def masks(self, frame: CameraFrame, names: Sequence[str]) -> list[np.ndarray]:
        """One ``[H, W]`` bool mask per name (empty where the detector finds nothing)."""
        out = []
        for name in names:
            found = self.box(frame.rgb, name)
            out.append(np.zeros(frame.shape, bool) if found is None else self.segment_box(frame.rgb, found[0]))
        return out
