"""Keypoints the arm brings along: boxes of eight corners, and the box around the end effector's start pose (the
same in every scene, so the maps keep the start where it is)."""

from __future__ import annotations

import numpy as np

from kpflow.geometry.angles import yaw_of

START_BOX = (0.10, 0.10, 0.10)  # m: the end-effector box around the start pose


def box_corners(centre_xy: np.ndarray, size_xy: np.ndarray, yaw: float, bottom: float, top: float) -> np.ndarray:
    """The 8 corners ``[8, 3]`` of an upright box: bottom face then top face, each counter-clockwise from
    ``(-x, -y)`` in the box's frame."""
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s], [s, c]])
    half = np.asarray(size_xy, float) / 2
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * half
    xy = square @ rot.T + np.asarray(centre_xy, float)
    return np.concatenate([np.c_[xy, np.full(4, bottom)], np.c_[xy, np.full(4, top)]])


def end_effector_box(position: np.ndarray, rotation: np.ndarray, size=START_BOX) -> np.ndarray:
    """The 8 corners ``[8, 3]`` of a ``size`` box centred on the end effector at ``position``, turned with its yaw."""
    p = np.asarray(position, float)
    return box_corners(p[:2], size[:2], yaw_of(rotation), p[2] - size[2] / 2, p[2] + size[2] / 2)
