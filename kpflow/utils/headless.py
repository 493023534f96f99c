"""Headless MuJoCo rendering on the CPU, chosen before MuJoCo is first imported."""

from __future__ import annotations

import ctypes.util
import os


def use_headless_gl() -> str:
    """Set ``MUJOCO_GL`` unless the user did: ``osmesa`` when Debian's libosmesa6 is installed (``make`` installs
    it), Mesa's software ``egl`` otherwise; PyOpenGL follows osmesa. Returns the choice."""
    if "MUJOCO_GL" not in os.environ:
        os.environ["MUJOCO_GL"] = "osmesa" if ctypes.util.find_library("OSMesa") else "egl"
    if os.environ["MUJOCO_GL"] == "osmesa":
        os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
    return os.environ["MUJOCO_GL"]
