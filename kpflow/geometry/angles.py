"""Planar angles: wrapping, the rotations by an angle in the plane and about the world's vertical, and a rotation's
yaw."""

from __future__ import annotations

import numpy as np


def wrap_angle(theta):
    """Angle(s) wrapped to ``[-pi, pi)``."""
    return (np.asarray(theta) + np.pi) % (2 * np.pi) - np.pi


def planar_rotation(angle) -> np.ndarray:
    """The 2-D rotation matrix ``[..., 2, 2]`` by ``angle`` (radians; a number or an array)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def yaw_rotation(yaw: float) -> np.ndarray:
    """The 3-D rotation by ``yaw`` (radians) about the world's vertical."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_of(rot: np.ndarray) -> float:
    """Yaw (rad) of a rotation's x axis in the world's XY plane."""
    return float(np.arctan2(rot[1, 0], rot[0, 0]))
