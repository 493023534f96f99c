"""Drawing Push-T scenes to RGB arrays (no display)."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from .geometry import AGENT_RADIUS, BAR, STEM, to_world
from .workspace import Workspace

# The standard env's colours.
WHITE, WALL, GOAL, BLOCK, AGENT = (255, 255, 255), (211, 211, 211), (144, 238, 144), (119, 136, 153), (65, 105, 225)
REGION, KEYPOINT, TARGET = (245, 245, 245), (220, 20, 60), (255, 140, 0)


def render_scene(
    workspace: Workspace,
    block_pose,
    goal_pose,
    agent_pos,
    size: int = 512,
    keypoints: np.ndarray | None = None,
    target=None,
) -> np.ndarray:
    """An RGB image ``[size, size, 3]`` (uint8) of the arena, the goal ghost, the block and the agent.

    The training region of a large workspace is shaded; ``keypoints`` ``[K, 2]`` are drawn as red dots and the
    action ``target`` as an orange cross. Image pixel (u, v) shows world point (u, v) * workspace.size / size.
    """
    scale = size / workspace.size
    img = Image.new("RGB", (size, size), WHITE)
    draw = ImageDraw.Draw(img)
    if workspace.region < workspace.size:
        draw.rectangle([0, 0, workspace.region * scale, workspace.region * scale], fill=REGION)
    lo, hi = workspace.wall_lo * scale, workspace.wall_hi * scale
    draw.rectangle([lo, lo, hi, hi], outline=WALL, width=max(1, round(4 * scale)))

    def polygon(pose, colour):
        for box in (BAR, STEM):
            draw.polygon([tuple(p) for p in to_world(pose, box) * scale], fill=colour)

    polygon(goal_pose, GOAL)
    polygon(block_pose, BLOCK)
    ax, ay = np.asarray(agent_pos, float) * scale
    r = AGENT_RADIUS * scale
    draw.ellipse([ax - r, ay - r, ax + r, ay + r], fill=AGENT)
    if target is not None:
        tx, ty = np.asarray(target, float) * scale
        c = max(2.0, 6 * scale)
        draw.line([tx - c, ty, tx + c, ty], fill=TARGET, width=2)
        draw.line([tx, ty - c, tx, ty + c], fill=TARGET, width=2)
    if keypoints is not None:
        d = max(1.5, 3 * scale)
        for x, y in np.asarray(keypoints, float) * scale:
            draw.ellipse([x - d, y - d, x + d, y + d], fill=KEYPOINT)
    return np.asarray(img)
