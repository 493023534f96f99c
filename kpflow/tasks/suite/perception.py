"""The benchmark tasks' keypoints from cameras: mask -> points -> oriented box -> the simulator extractor's keypoints.

For each object, the pixels its mask covers in every camera are lifted to world points
(:meth:`~kpflow.vision.cameras.CameraFrame.points`), and their :func:`~kpflow.vision.boxes.fit_footprint_box` (the
minimum-area rectangle of the footprint, the top from the highest voxels; the paper's Sec. 3.3) gives the object's
pose as its kind reads it:

* ``cube``: the centre of the rectangle, half a side below the top (the side: the top's height above what the cube
  stands on, else the rectangle's mean side); its yaw is the rectangle's (a quarter turn is the same cube);
* ``can``: the rectangle's centre, half the can's height below the top (a cylinder has no yaw);
* ``nut`` (its handle and ring kinds alike): the rectangle's longer axis is the handle's; the ring is at the end
  whose points spread wider across that axis, its centre the rectangle's short half side in from that end (the ring
  is square), the body 1 cm below the top;
* ``peg``: the rectangle's centre, the body a peg's half length below the top;
* ``bin``: the rectangle's centre, its yaw a quarter turn from the rectangle's longer axis (the bin's longer sides
  run along its y), the body 0.1 m below the rim.

:func:`~.keypoints.object_keypoints` then places the same named keypoints as the simulator-based extractor, in the
same order, with the symmetric ones ordered by the same reference yaw. The gripper's keypoints come from the robot
itself (its forward kinematics), as on a real arm.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from scipy import ndimage

from kpflow.geometry.angles import yaw_of, yaw_rotation
from kpflow.vision.boxes import FootprintBox, fit_footprint_box
from kpflow.vision.cameras import CameraFrame
from kpflow.vision.depth_filter import smooth_depth, temporal_mean
from kpflow.vision.keypoint_source import KeypointSource
from kpflow.vision.noise import CameraNoise
from kpflow.vision.occlusion import FootprintGate, OccludedRead
from kpflow.vision.pose_filter import PoseFilter
from kpflow.vision.segmentation import InstanceSegmenter, Segmenter

from .cameras import DEFAULT_CAMERAS, SuiteCameras, object_geoms
from .keypoints import (
    ObjectPose,
    object_keypoints,
    policy_keypoints,
    policy_objects,
    pose_keypoints,
)
from .objects import SYMMETRY, object_kind
from .specs import TaskSpec


def object_points(frames: Sequence[CameraFrame], masks: Sequence[np.ndarray], erode: int = 2, smooth: int = 5,
                  support_margin: float | None = 0.005) -> tuple[np.ndarray, float | None]:  # fmt: skip
    """World points ``[N, 3]`` of one object, and the height of what it stands on (None: not seen).

    The pixels of its mask in each frame, ``erode`` pixels in from the mask's edge (an edge pixel's depth may be the
    surface behind the object, and a segmenter's mask may spill over), their depth smoothed within the mask
    (:func:`~kpflow.vision.depth_filter.smooth_depth`, ``smooth x smooth`` windows; 1: as measured), lifted and
    stacked. The support's height is the median height of the points in a ring 3 to 8 pixels around the masks,
    trusted only where the object's lowest points (their 2nd percentile) lie within ``support_margin`` + 1 cm of it
    (a held object's ring is the fingers and the floor far below: None); with ``support_margin``, the object's points
    less than that far above it are dropped."""
    if len(frames) != len(masks):
        raise ValueError(f"one mask per frame: got {len(masks)} masks for {len(frames)} frames")
    masks = [np.asarray(m, bool) for m in masks]
    rings = [ndimage.binary_dilation(m, iterations=8) & ~ndimage.binary_dilation(m, iterations=3) for m in masks]
    if erode:
        masks = [ndimage.binary_erosion(m, iterations=int(erode)) for m in masks]
    smoothed = [replace(f, depth=smooth_depth(f.depth, m, smooth)) for f, m in zip(frames, masks)]
    points = np.concatenate([f.points(m) for f, m in zip(smoothed, masks)] or [np.zeros((0, 3))])
    ring = np.concatenate([f.points(r) for f, r in zip(frames, rings)] or [np.zeros((0, 3))])
    support = float(np.median(ring[:, 2])) if len(ring) >= 10 and len(points) >= 10 else None
    if support is not None and abs(np.percentile(points[:, 2], 2) - support) > (support_margin or 0.0) + 0.01:
        support = None  # it does not stand on what surrounds it in the images
    if support_margin is not None and support is not None:
        points = points[points[:, 2] > support + support_margin]
    return points, support


def pose_from_box(
    kind: str, box: FootprintBox, support: float | None = None
) -> tuple[np.ndarray, np.ndarray, float | None]:
    """``(pos [3], rot [3, 3], half)`` of an object of ``kind`` whose :class:`FootprintBox` is ``box`` (module
    docstring; each kind's file of :mod:`.objects`), standing on a surface at height ``support`` (None: unknown);
    ``half``: a cube's half side, else None."""
    return object_kind(kind).pose_from_box(box, support)


def perceived_object_keypoints(kind: str, points: np.ndarray, reference_yaw: float = 0.0, support: float | None = None,
                               voxel: float = 0.002, top_fraction: float = 0.1) -> np.ndarray:  # fmt: skip
    """Keypoints ``[N, 3]`` of an object of ``kind`` seen as world ``points [M, 3]`` standing at height ``support``
    (module docstring): the same as :func:`~.keypoints.object_keypoints` gives for its true pose, up to perception's
    error."""
    pos, rot, half = pose_from_box(kind, fit_footprint_box(points, voxel, top_fraction), support)
    return object_keypoints(kind, pos, rot, reference_yaw, half)


class CameraKeypoints:
    """The objects' poses and keypoints in a :class:`~.env.SuiteEnv` seen by its cameras (module docstring), with a
    sensor's errors (``keypoints=camera``).

    Args:
        cameras: which cameras and what image size (the environment must render).
        noise: the sensor's errors (:class:`~kpflow.vision.noise.CameraNoise`; ``CameraNoise.off()``: the clean render).
            Each camera's calibration error is drawn once from ``seed`` (a calibration is done once); depth and mask
            errors are drawn afresh for every frame, from a stream that :meth:`reseed` restarts.
        segmenter: which pixels are which object (None: the renderer's instance segmentation of each object's geoms).
        seed: seeds the noise; the same seed and scenes give the same keypoints.
        erode, smooth, voxel, top_fraction: see :func:`object_points` and :func:`~kpflow.vision.boxes.fit_footprint_box`.
        temporal: depth frames averaged per capture (the scene is still where the cameras are read: a segment's
            start, a policy's decision).
        pose_filter: each object's reads filtered (:class:`~kpflow.vision.pose_filter.PoseFilter`: the median of
            the reads that agree, outliers rejected) within a scene; None: every read as it comes.
        occlusion: a read whose footprint is not the object's first one in the scene refused
            (:class:`~kpflow.vision.occlusion.FootprintGate`: part of it hidden, by the jaws above it), the object
            kept where it was last seen (:attr:`occluded` counts them); None: every read taken.
    """

    per_step = False  #: a capture costs about a second: read where a policy decides, not at every control step

    def __init__(self, cameras: SuiteCameras | None = None, noise: CameraNoise | None = None, segmenter: Segmenter | None = None,
                 seed: int = 0, erode: int = 2, smooth: int = 5, voxel: float = 0.002, top_fraction: float = 0.1,
                 temporal: int = 1, pose_filter: PoseFilter | None = None, occlusion: FootprintGate | None = None) -> None:  # fmt: skip
        if int(temporal) != temporal or temporal < 1:
            raise ValueError(f"temporal must be a whole number of frames >= 1; got {temporal!r}")
        self.temporal = int(temporal)
        self.cameras = cameras or SuiteCameras()
        self.noise = CameraNoise() if noise is None else noise
        self.segmenter, self.erode, self.smooth = segmenter, int(erode), int(smooth)
        self.voxel, self.top_fraction = float(voxel), float(top_fraction)
        self.seed = int(seed)
        self.pose_filter, self.occlusion = pose_filter, occlusion
        self.reseed()

    @classmethod
    def from_source(cls, source: KeypointSource) -> CameraKeypoints:
        """The perception a :class:`~kpflow.vision.keypoint_source.KeypointSource` (``kind="camera"``) describes."""
        cameras = SuiteCameras(source.cameras or DEFAULT_CAMERAS, source.height, source.width)
        return cls(
            cameras,
            source.noise,
            source.segmenter,
            source.seed,
            temporal=source.temporal,
            pose_filter=source.pose_filter(),
            occlusion=source.footprint_gate(),
        )

    def reseed(self, *keys: int) -> None:
        """Start a new scene: restart the depth and mask errors' stream at ``(seed, *keys)`` (e.g. an attempt's
        index), so that what a scene shows does not depend on which scenes were seen before, and forget what was
        seen and held."""
        self.rng = np.random.default_rng([self.seed, *map(int, keys)])
        self.last: dict[str, ObjectPose] = {}  # each object's pose when last seen
        self.held: dict[str, ObjectPose] = {}  # held objects' poses in the grip site's frame
        self.occluded = 0  # reads refused as partly hidden, this scene
        for per_object in (self.pose_filter, self.occlusion):
            if per_object is not None:
                per_object.reset()

    def frames(self, env) -> list[CameraFrame]:
        """The cameras' frames of the scene now, as the sensor gives them (noisy depth, the calibrated pose)."""
        return self.sense(self.cameras.capture(env))

    def sense(self, frames: Sequence[CameraFrame]) -> list[CameraFrame]:
        """Rendered ``frames`` (one per camera, in :attr:`cameras`' order) as the sensor gives them: with
        ``temporal`` > 1, that many noisy frames of the still scene averaged (:func:`~kpflow.vision.depth_filter.temporal_mean`)."""
        out = []
        for i, frame in enumerate(frames):
            calibration = np.random.default_rng([self.seed, 1, i])  # the same error at every capture
            sensed = self.noise.frame(frame, self.rng, calibration)
            if self.temporal > 1:
                depths = [sensed.depth] + [self.noise.depth(frame.depth, self.rng) for _ in range(self.temporal - 1)]
                sensed = replace(sensed, depth=temporal_mean(depths))
            out.append(sensed)
        return out

    def _segmenter(self, env) -> Segmenter:
        if self.segmenter is not None:
            return self.segmenter
        names = [*env.object_body, *env.fixture_body]
        return InstanceSegmenter({n: object_geoms(env, n) for n in names})

    def pose(self, env, spec: TaskSpec, frames: Sequence[CameraFrame], name: str) -> ObjectPose:
        """The pose of object or fixture ``name`` seen in ``frames`` (:func:`pose_from_box`; through :attr:`pose_filter`
        where there is one), remembered as where it was last seen; a read :attr:`occlusion` refuses gives where it
        was last seen (``ValueError`` when it never was)."""
        segmenter = self._segmenter(env)
        masks = [self.noise.mask(segmenter.masks(f, [name])[0], self.rng) for f in frames]
        kind = spec.kinds[name]
        try:
            points, support = object_points(frames, masks, self.erode, self.smooth)
            box = fit_footprint_box(points, self.voxel, self.top_fraction)
        except ValueError as e:
            raise ValueError(
                f"{spec.name}: cannot place {name!r} from the cameras {[f.name for f in frames]}: {e}"
            ) from None
        if self.occlusion is not None:
            try:
                self.occlusion.check(name, box)
            except OccludedRead as e:
                if name not in self.last:
                    raise ValueError(f"{spec.name}: {e}, and it was never seen whole") from None
                self.occluded += 1
                return self.last[name]
        pose = ObjectPose(*pose_from_box(kind, box, support))
        if self.pose_filter is not None:
            seen = self.pose_filter.update(name, pose.pos, yaw_of(pose.rot), SYMMETRY[kind], pose.half)
            pose = ObjectPose(seen.pos, yaw_rotation(seen.yaw), seen.half)
        self.last[name] = pose
        return pose

    def poses(self, env, spec: TaskSpec, names: Sequence[str]) -> dict[str, ObjectPose]:
        """The poses of objects ``names`` from one fresh capture; a held one's (:meth:`grasped`) carried by the jaws
        from where it was last seen, since the hand hides a held object from the cameras."""
        held = {n: self.carried(env, n) for n in names if n in self.held}
        frames = self.frames(env) if len(held) < len(names) else []
        return {n: held[n] if n in held else self.pose(env, spec, frames, n) for n in names}

    def grasped(self, env, name: str, at: tuple[np.ndarray, np.ndarray]) -> None:
        """The jaws close on ``name`` with the grip site commanded to ``at`` (position, rotation): from here on it
        moves with them, sitting where it was last seen relative to that pose (the grasp as planned; the arm's own
        pose lags the command by up to a centimetre while it closes)."""
        if name in self.last:
            pos, rot = at
            seen = self.last[name]
            self.held[name] = ObjectPose(rot.T @ (seen.pos - pos), rot.T @ seen.rot, seen.half)

    def released(self, env, name: str) -> None:
        """The jaws open: ``name`` is seen by the cameras again, and until a read of it is whole it lies where the
        jaws carried it (not where it was seen before the grasp: the hand still hides it as it lets go); its
        filtered reads are forgotten."""
        if name in self.held:
            self.last[name] = self.carried(env, name)
        self.missed(name)

    def missed(self, name: str) -> None:
        """The jaws closed on nothing: ``name`` is not held, and lies where the cameras last saw it."""
        self.held.pop(name, None)
        if self.pose_filter is not None:
            self.pose_filter.forget(name)  # its footprint stays: what was set down or dropped lies as it did

    def carried(self, env, name: str) -> ObjectPose:
        """Where held object ``name`` is now, carried by the jaws since :meth:`grasped`."""
        pos, rot = env.ee_pose()
        local = self.held[name]
        return ObjectPose(pos + rot @ local.pos, rot @ local.rot, local.half)

    def scene_keypoints(self, env, spec: TaskSpec, frames: Sequence[CameraFrame], name: str, reference_yaw: float = 0.0,
                        kind: str | None = None) -> np.ndarray:  # fmt: skip
        """:func:`~.keypoints.scene_keypoints` of object or fixture ``name`` seen in ``frames``."""
        return pose_keypoints(spec, name, self.pose(env, spec, frames, name), reference_yaw, kind)

    def policy_keypoints(self, env, spec: TaskSpec) -> np.ndarray:
        """:func:`~.keypoints.policy_keypoints` with the objects seen by the cameras: the object to pick and its goal
        from a fresh capture, the grip site and the finger pads from the robot."""
        return policy_keypoints(env, spec, self.poses(env, spec, policy_objects(spec)))
