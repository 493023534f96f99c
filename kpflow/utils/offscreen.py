"""robosuite's offscreen renderer, used so that one environment's GL context never damages another's.

robosuite renders into whichever GL context is current, and frees a renderer (``MjRenderContext.__del__``, whenever
the garbage collector gets to it) with whichever is current then: freeing environment B's renderer while A's context
is current deletes A's framebuffers, and every later frame of A is noise colour with a z-buffer of garbage (values
of 1e38, NaN) -- on OSMesa and EGL alike. So:

- :func:`render` makes the environment's own context current before each frame (another environment's may be);
- :func:`own_renderer` frees an environment's renderer in its own context when the environment is collected
  (robosuite's own ``__del__`` then finds nothing left to free);
- :func:`metric_depth` refuses a z-buffer that is not finite and within ``[0, 1]`` (:class:`BrokenRender`, naming
  the camera) instead of clipping it into plausible depths, then converts it to metres
  (``robosuite.utils.camera_utils.get_real_depth_map``).

:class:`BrokenRender` is a ``RuntimeError``, not a ``ValueError``: perception treats a ``ValueError`` as an object it
could not see this time, and a broken sensor is not that.
"""

from __future__ import annotations

import os
import weakref

import numpy as np


class BrokenRender(RuntimeError):
    """The renderer returned a frame that no camera could see (its GL context was damaged)."""


def _free_in_own_context(context) -> None:
    """Free a robosuite render context's MuJoCo objects with its own GL context current (then ``con.free()`` in
    robosuite's ``__del__`` finds them freed already)."""
    try:
        context.gl_ctx.make_current()
        context.con.free()
    except Exception:  # noqa: BLE001 -- at interpreter exit the GL library may be gone: nothing left to protect
        pass


def own_renderer(env) -> None:
    """Make sure the offscreen renderer of ``env.sim`` is freed in its own GL context when ``env`` (the environment
    holding it) is collected; once per renderer."""
    context = env.sim._render_context_offscreen
    if context is not None and not getattr(context, "_kpflow_owned", False):
        context._kpflow_owned = True
        weakref.finalize(env, _free_in_own_context, context)


def render(env, camera: str, height: int, width: int, depth: bool = False, segmentation: bool = False):
    """``env.sim.render`` of ``camera`` at ``height x width`` in the renderer's own GL context (rows bottom-up, as
    OpenGL reads them); ``ValueError`` when ``env`` has no offscreen renderer."""
    context = env.sim._render_context_offscreen
    if context is None:
        raise ValueError("this environment has no offscreen renderer: build it with render=True to take camera frames")
    own_renderer(env)  # a renderer made after the env was built (robosuite's hard reset) is owned too
    context.gl_ctx.make_current()
    return env.sim.render(
        camera_name=camera, width=int(width), height=int(height), depth=depth, segmentation=segmentation
    )


def metric_depth(sim, zbuffer: np.ndarray, camera: str) -> np.ndarray:
    """The depth in metres of a rendered normalised z-buffer (same shape, float64); :class:`BrokenRender` naming
    ``camera`` when any value is not finite or outside ``[0, 1]`` (module docstring)."""
    from robosuite.utils import camera_utils

    z = np.asarray(zbuffer)
    bad = ~(np.isfinite(z) & (z >= 0.0) & (z <= 1.0))
    if bad.any():
        raise BrokenRender(
            f"camera {camera!r} rendered a broken depth image ({int(bad.sum())} of {z.size} pixels not a z-buffer value "
            f"in [0, 1]): its GL context (MUJOCO_GL={os.environ.get('MUJOCO_GL', '?')}) was damaged; build the environment again"
        )
    return np.asarray(camera_utils.get_real_depth_map(sim, z), dtype=np.float64)
