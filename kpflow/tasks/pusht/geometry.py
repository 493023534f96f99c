"""Geometry of the Push-T block: its two boxes, its 12 keypoints and the coverage score.

A pose is ``(x, y, theta)`` of the block's body origin, exactly the ``block_pos, block_angle`` of the standard
Push-T state (Diffusion Policy's ``PushTEnv``): a body point ``p`` lies at ``R(theta) p + (x, y)`` in the world.
The origin is the middle of the bar's lower edge; the stem grows along +y. World coordinates are pixels of the
arena, with y pointing down on screen as in the standard renderer.

Keypoint order (fixed; ``KEYPOINT_NAMES`` spells it out). For each box of the T: its 4 corners, then the midpoints
of its two long edges. The bar comes first, then the stem::

     0 (-60,  0)   1 ( 60,  0)   2 ( 60, 30)   3 (-60, 30)   4 (  0,  0)   5 (  0, 30)    bar, 120 x 30
     6 (-15, 30)   7 ( 15, 30)   8 ( 15,120)   9 (-15,120)  10 (-15, 75)  11 ( 15, 75)    stem, 30 x 90

An observation stacks the block's 12, the goal's 12 and the agent's position: 25 keypoints (:data:`PUSHT_BLOCK`,
:data:`PUSHT_GOAL`, then the agent). A K-CFM reads it in the goal's frame (:func:`goal_frame`), a source index
weighs the three groups (:func:`pusht_weights`).
"""

from __future__ import annotations

import numpy as np
import shapely

#: The bar and the stem, as the standard env's ``add_tee`` builds them (scale 30, length 4), in body coordinates.
BAR = np.array([(-60.0, 30.0), (60.0, 30.0), (60.0, 0.0), (-60.0, 0.0)])
STEM = np.array([(-15.0, 30.0), (-15.0, 120.0), (15.0, 120.0), (15.0, 30.0)])

#: Outline of the T (counter-clockwise on screen with y down), for routing and drawing.
OUTLINE = np.array(
    [(-60.0, 0.0), (60.0, 0.0), (60.0, 30.0), (15.0, 30.0), (15.0, 120.0), (-15.0, 120.0), (-15.0, 30.0), (-60.0, 30.0)]
)

T_KEYPOINTS = np.array(
    [
        (-60.0, 0.0), (60.0, 0.0), (60.0, 30.0), (-60.0, 30.0), (0.0, 0.0), (0.0, 30.0),
        (-15.0, 30.0), (15.0, 30.0), (15.0, 120.0), (-15.0, 120.0), (-15.0, 75.0), (15.0, 75.0),
    ]
)  # fmt: skip
_T_NAMES = (
    "bar_corner_0", "bar_corner_1", "bar_corner_2", "bar_corner_3", "bar_mid_low", "bar_mid_high",
    "stem_corner_0", "stem_corner_1", "stem_corner_2", "stem_corner_3", "stem_mid_left", "stem_mid_right",
)  # fmt: skip
KEYPOINT_NAMES = tuple(f"block_{n}" for n in _T_NAMES) + tuple(f"goal_{n}" for n in _T_NAMES) + ("agent",)
N_T_KEYPOINTS = len(T_KEYPOINTS)  # 12
N_KEYPOINTS = 2 * N_T_KEYPOINTS + 1  # 25
T_AREA = 120.0 * 30.0 + 30.0 * 90.0  # 6300 px^2
AGENT_RADIUS = 15.0
PUSHT_BLOCK = tuple(range(N_T_KEYPOINTS))  # the block's keypoints in a Push-T observation
PUSHT_GOAL = tuple(range(N_T_KEYPOINTS, 2 * N_T_KEYPOINTS))  # the goal's, in the block's order


def pusht_weights(block: float = 1.0, goal: float = 1.0, agent: float = 1.0) -> np.ndarray:
    """Per-keypoint weights ``[25]`` for Push-T observations: block T (12), goal T (12), agent (1)."""
    for name, w in (("block", block), ("goal", goal), ("agent", agent)):
        if not np.isfinite(w) or w < 0:
            raise ValueError(f"keypoint weight {name} must be finite and >= 0, got {w}")
    return np.concatenate([np.full(N_T_KEYPOINTS, block), np.full(N_T_KEYPOINTS, goal), [agent]]).astype(np.float32)


def goal_frame() -> dict:
    """The goal T as a K-CFM's goal frame (``KCFM(goal_frame=...)``, :mod:`kpflow.policies.kcfm`): its keypoints in
    an observation (:data:`PUSHT_GOAL`) and where they lie in the T's body frame (:data:`T_KEYPOINTS`), so the frame
    fitted to an observed goal is the goal's pose ``(x, y, theta)``."""
    return {"keypoints": list(PUSHT_GOAL), "template": T_KEYPOINTS.tolist()}


def to_world(pose, points: np.ndarray) -> np.ndarray:
    """Body points ``[..., 2]`` to world coordinates under ``pose = (x, y, theta)``: ``R(theta) p + t``."""
    x, y, theta = (float(v) for v in pose)
    c, s = np.cos(theta), np.sin(theta)
    px, py = points[..., 0], points[..., 1]
    return np.stack([c * px - s * py + x, s * px + c * py + y], axis=-1)


def to_body(pose, points: np.ndarray) -> np.ndarray:
    """World points ``[..., 2]`` to body coordinates of ``pose`` (the inverse of :func:`to_world`)."""
    x, y, theta = (float(v) for v in pose)
    c, s = np.cos(theta), np.sin(theta)
    dx, dy = points[..., 0] - x, points[..., 1] - y
    return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1)


def t_keypoints(pose) -> np.ndarray:
    """The 12 keypoints ``[12, 2]`` of a T at ``pose``."""
    return to_world(pose, T_KEYPOINTS)


def observation_keypoints(block_pose, goal_pose, agent_pos) -> np.ndarray:
    """The 25 observation keypoints ``[25, 2]``: block T, goal T, agent."""
    return np.concatenate([t_keypoints(block_pose), t_keypoints(goal_pose), np.asarray(agent_pos, float)[None]])


def t_polygon(pose) -> shapely.Polygon:
    """The T at ``pose`` as one shapely polygon."""
    return shapely.polygons(to_world(pose, OUTLINE))


def outline_coverage(block_outline: np.ndarray, goal: shapely.Polygon) -> float:
    """Coverage of the ``goal`` polygon by the T whose world outline is ``block_outline`` ``[8, 2]``.

    ``area(goal & block) / area(goal)``, the standard env's score, by shapely; 0 without a shapely call when the
    bounding boxes are disjoint.
    """
    x0, y0, x1, y1 = goal.bounds
    lo, hi = block_outline.min(0), block_outline.max(0)
    if lo[0] > x1 or lo[1] > y1 or hi[0] < x0 or hi[1] < y0:
        return 0.0
    return float(shapely.intersection(goal, shapely.polygons(block_outline)).area / T_AREA)


def coverage(block_pose, goal_pose) -> float:
    """Share of the goal T covered by the block T: ``area(goal & block) / area(goal)``."""
    return outline_coverage(to_world(block_pose, OUTLINE), t_polygon(goal_pose))
