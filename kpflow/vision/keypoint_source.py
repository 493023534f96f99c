"""Where a task reads its keypoints from (the config group ``keypoints``): the simulator's object poses, or
cameras with a sensor's errors.

``keypoints=sim`` (the default) reads every object's pose from the simulator; ``keypoints=camera`` renders RGB-D
frames and perceives the objects in them (for the robosuite tasks :class:`~kpflow.tasks.suite.perception.CameraKeypoints`,
for packing its top-down camera), with :class:`~kpflow.vision.noise.CameraNoise`'s errors. A task turns this
description into its own perception; the gripper's keypoints always come from the robot's kinematics.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from .noise import CameraNoise
from .occlusion import FootprintGate
from .pose_filter import PoseFilter
from .segmentation import Segmenter

KINDS = ("sim", "camera")


@dataclass(frozen=True)
class KeypointSource:
    """``kind``: ``"sim"`` or ``"camera"``; for cameras which ones (``cameras``; None: the task's own), the
    image size ``height x width``, the sensor's ``noise``, the ``seed`` that draws it (the same seed and scenes
    give the same keypoints), the depth frames averaged per capture (``temporal``) and the ``segmenter`` that finds
    each object's pixels
    (:class:`~kpflow.vision.segmentation.Segmenter`, e.g. :class:`~kpflow.vision.grounded_sam.GroundedSAM`; None:
    the renderer's instance masks); ``filter``: the options of a :class:`~kpflow.vision.pose_filter.PoseFilter` over
    each object's reads (``window``, ``gate``, ``gate_deg``, ``patience``; None: every read as it comes);
    ``occlusion_gate``: the tolerance (m) of a :class:`~kpflow.vision.occlusion.FootprintGate` that refuses a
    partly hidden object's reads (None: every read taken)."""

    kind: str = "sim"
    cameras: tuple[str, ...] | None = None
    height: int = 480
    width: int = 640
    noise: CameraNoise = field(default_factory=CameraNoise)
    seed: int = 0
    temporal: int = 1
    segmenter: Segmenter | None = None
    filter: Mapping | None = None
    occlusion_gate: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"keypoints must come from one of {list(KINDS)}; got {self.kind!r}")
        if self.cameras is not None:
            if isinstance(self.cameras, str) or not len(self.cameras):
                raise ValueError(f"cameras must be a non-empty list of camera names (or null); got {self.cameras!r}")
            object.__setattr__(self, "cameras", tuple(str(c) for c in self.cameras))
        if int(self.height) < 16 or int(self.width) < 16:
            raise ValueError(f"camera images must be at least 16 x 16 pixels; got {self.height} x {self.width}")
        if not isinstance(self.noise, CameraNoise):
            object.__setattr__(self, "noise", CameraNoise(**dict(self.noise)))
        if self.filter is not None:
            object.__setattr__(self, "filter", dict(self.filter))
            self.pose_filter()  # refuses bad options now
        if self.occlusion_gate is not None:
            self.footprint_gate()  # refuses a bad tolerance now
        if self.segmenter is not None and not isinstance(self.segmenter, Segmenter):
            raise TypeError(f"segmenter must have masks(frame, names); got {type(self.segmenter).__name__}")

    def pose_filter(self) -> PoseFilter | None:
        """A new :class:`~kpflow.vision.pose_filter.PoseFilter` with :attr:`filter`'s options (None without)."""
        if self.filter is None:
            return None
        unknown = set(self.filter) - {"window", "gate", "gate_deg", "patience"}
        if unknown:
            raise ValueError(
                f"unknown pose filter options {sorted(unknown)}; it takes window, gate, gate_deg, patience"
            )
        return PoseFilter(**self.filter)

    def footprint_gate(self) -> FootprintGate | None:
        """A new :class:`~kpflow.vision.occlusion.FootprintGate` of tolerance :attr:`occlusion_gate` (None without)."""
        return None if self.occlusion_gate is None else FootprintGate(float(self.occlusion_gate))

    @property
    def camera(self) -> bool:
        """Whether the keypoints come from cameras."""
        return self.kind == "camera"
