"""An object's oriented box from its points: the paper's recipe for 3-D keypoints (Sec. 3.3).

The points of one object (a segmented, lifted point cloud, world frame, z up) are thinned to one per voxel (the mean
of the points in each ``voxel``-sided cube) and only the largest cluster of voxels, cells of side ``link`` that touch,
is kept (stray returns: a mask pixel whose depth is the surface behind the object, a see-through wall, a
speck of noise), then

* the **footprint** is the minimum-area rectangle of the voxels' ``(x, y)`` (shapely's
  ``minimum_rotated_rectangle``, rotating calipers over the convex hull): its centre, its axes and half sides;
* the **top** is the median height of the highest ``top_fraction`` of the voxels (at least one): the highest
  voxels, but not the single highest, which depth noise lifts.

:class:`FootprintBox` reports them; a task turns a box into its objects' keypoints (what the box means depends on
the object: a cube's centre is half a side below its top, a nut's ring is at one end of its rectangle).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from scipy import ndimage


@dataclass(frozen=True)
class FootprintBox:
    """A footprint rectangle and a top height (module docstring).

    Attributes:
        centre: ``[2]`` the rectangle's centre ``(x, y)``.
        yaw: the direction of its longer axis (rad, in ``(-pi/2, pi/2]``; a square's is either axis).
        half: ``[2]`` half sides along the longer and the shorter axis.
        top: the top's height.
        voxels: ``[M, 3]`` the voxel centres it was fitted on.
    """

    centre: np.ndarray
    yaw: float
    half: np.ndarray
    top: float
    voxels: np.ndarray

    @property
    def axis(self) -> np.ndarray:
        """``[2]`` the unit vector of the longer axis."""
        return np.array([np.cos(self.yaw), np.sin(self.yaw)])


def voxel_centres(points: np.ndarray, voxel: float) -> np.ndarray:
    """The mean point ``[M, 3]`` of each occupied ``voxel``-sided cell of ``points [N, 3]`` (sorted by cell)."""
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(0)
    span = cells.max(0) + 1
    _, inverse, counts = np.unique(
        (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2], return_inverse=True, return_counts=True
    )
    sums = np.stack([np.bincount(inverse, points[:, i], len(counts)) for i in range(3)], -1)
    return sums / counts[:, None]


def largest_cluster(points: np.ndarray, link: float) -> np.ndarray:
    """The points ``[M, 3]`` of the largest connected part of ``points [N, 3]``: the points are binned into cells of
    side ``link``, cells touching at a face, an edge or a corner are connected (``scipy.ndimage.label``), and the
    component holding the most points is kept."""
    if len(points) < 2:
        return points
    cells = np.floor(points / link).astype(np.int64)
    cells -= cells.min(0)
    grid = np.zeros(cells.max(0) + 1, bool)
    grid[tuple(cells.T)] = True
    labels, _ = ndimage.label(grid, structure=np.ones((3, 3, 3), bool))
    of_point = labels[tuple(cells.T)]
    return points[of_point == np.argmax(np.bincount(of_point))]


def fit_footprint_box(
    points: np.ndarray, voxel: float = 0.002, top_fraction: float = 0.1, link: float | None = 0.01, min_voxels: int = 4
) -> FootprintBox:
    """The :class:`FootprintBox` of one object's world points ``[N, 3]`` (module docstring).

    Raises:
        ValueError: points that are not ``[N, 3]`` and finite, a ``voxel``, ``link`` or ``top_fraction`` out of range, or fewer
            than ``min_voxels`` occupied voxels (the object is not seen: occluded, out of view or not segmented).
    """
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or not np.isfinite(p).all():
        raise ValueError(f"points must be finite [N, 3]; got shape {list(p.shape)}")
    if not voxel > 0 or not 0 < top_fraction <= 1 or (link is not None and not link > 0):
        raise ValueError(
            f"voxel and link must be > 0 (link may be None) and top_fraction in (0, 1]; got {voxel}, {link} and {top_fraction}"
        )
    v = voxel_centres(p, voxel) if len(p) else np.zeros((0, 3))
    v = v if link is None else largest_cluster(v, link)
    if len(v) < min_voxels:
        raise ValueError(
            f"the object is seen in {len(v)} voxels of {voxel * 1e3:g} mm, fewer than {min_voxels}: occluded, out of view or not segmented"
        )
    rect = shapely.minimum_rotated_rectangle(shapely.multipoints(v[:, :2]))
    corners = np.asarray(rect.exterior.coords)[:4] if rect.geom_type == "Polygon" else _degenerate(v[:, :2])
    centre = corners.mean(0)
    sides = corners[1:3] - corners[:2]  # two adjacent sides
    lengths = np.linalg.norm(sides, axis=1)
    longer = int(np.argmax(lengths))
    direction = sides[longer] / max(lengths[longer], 1e-12)
    yaw = float(np.arctan2(direction[1], direction[0]))
    yaw = yaw - np.pi if yaw > np.pi / 2 else yaw + np.pi if yaw <= -np.pi / 2 else yaw
    z = np.sort(v[:, 2])
    top = float(np.median(z[-max(1, int(round(top_fraction * len(z)))) :]))
    return FootprintBox(centre, yaw, np.sort(lengths)[::-1] / 2, top, v)


def _degenerate(xy: np.ndarray) -> np.ndarray:
    """Four corners of a collinear footprint (a line or a point): its ends, twice."""
    a, b = xy[np.argmin(xy @ [1.0, 0.5])], xy[np.argmax(xy @ [1.0, 0.5])]
    return np.stack([a, b, b, a])
