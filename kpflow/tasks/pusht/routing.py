"""Paths for the Push-T agent: around the block without touching it, then retimed into smooth, speed-bounded targets.

:func:`shortest_path` searches the visibility graph of the block's outline padded by the agent radius (the
classic exact shortest path among polygonal obstacles); :func:`retime` turns a polyline into one target per
control step with bounded speed and acceleration, like a hand moving a mouse.
"""

from __future__ import annotations

import numpy as np
import shapely
from scipy.sparse.csgraph import dijkstra


def padded_obstacle(outline: np.ndarray, pad: float) -> shapely.Polygon:
    """The polygon ``outline`` grown by ``pad`` with mitred corners (the agent's centre must stay outside it)."""
    return shapely.Polygon(outline).buffer(pad, join_style="mitre", mitre_limit=3.0)


def _free(a: np.ndarray, b: np.ndarray, obstacle) -> bool:
    return not shapely.intersects(shapely.LineString([a, b]), obstacle)


def shortest_path(start, goal, obstacle: shapely.Polygon, bounds: tuple[float, float]) -> np.ndarray | None:
    """Shortest polyline ``[P, 2]`` from ``start`` to ``goal`` that stays outside ``obstacle``, or None.

    Nodes are the obstacle's vertices pushed 1 px outwards (so that edges along its sides count as free) and kept
    inside ``bounds`` (lo, hi) on both axes; edges join mutually visible nodes; scipy's Dijkstra finds the path.
    The obstacle check uses the obstacle itself, so ``start``/``goal`` inside it give None.
    """
    start, goal = np.asarray(start, float), np.asarray(goal, float)
    if _free(start, goal, obstacle):
        return np.stack([start, goal])
    ring = np.asarray(obstacle.buffer(1.0, join_style="mitre", mitre_limit=3.0).exterior.coords)[:-1]
    lo, hi = bounds
    ring = ring[np.all((ring >= lo) & (ring <= hi), axis=1)]
    nodes = np.concatenate([start[None], goal[None], ring])
    n = len(nodes)
    weights = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1, n):
            if _free(nodes[i], nodes[j], obstacle):
                weights[i, j] = weights[j, i] = np.linalg.norm(nodes[i] - nodes[j]) + 1e-9
    dist, pred = dijkstra(weights, indices=0, return_predecessors=True)
    if not np.isfinite(dist[1]):
        return None
    path, k = [1], 1
    while k != 0:
        k = pred[k]
        path.append(k)
    return nodes[path[::-1]]


def path_length(path: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())


def smooth(path: np.ndarray, obstacle: shapely.Polygon, iterations: int = 2) -> np.ndarray:
    """Chaikin corner cutting, keeping each cut only where the smoothed polyline stays outside ``obstacle``."""
    for _ in range(iterations):
        if len(path) < 3:
            return path
        out = [path[0]]
        for a, b in zip(path[:-1], path[1:]):
            out += [0.75 * a + 0.25 * b, 0.25 * a + 0.75 * b]
        out.append(path[-1])
        candidate = np.asarray(out)
        if shapely.intersects(shapely.LineString(candidate), obstacle):
            return path
        path = candidate
    return path


def retime(path: np.ndarray, v_max: float, accel: float, v_start: float = 0.0, v_end: float = 0.0) -> np.ndarray:
    """Targets ``[N, 2]`` along ``path``, one per control step, ending exactly at ``path[-1]``.

    The speed (px per step) starts at ``v_start``, rises by at most ``accel`` per step up to ``v_max`` and falls
    in time to reach ``v_end`` at the end: a trapezoidal profile along the arc length.
    """
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    total = float(seg.sum())
    if total < 1e-9:
        return path[-1:].copy()
    s, v, arc = 0.0, float(v_start), []
    while s < total - 1e-9:
        # fastest speed from which steps v, v - accel, ... still end at v_end within the remaining distance
        rest = max(total - s, 0.0)
        brake = 0.5 * (-accel + np.sqrt(accel**2 + 4.0 * (2.0 * accel * rest + v_end**2 - accel * v_end)))
        v = max(min(v + accel, v_max, brake), min(accel, total - s))
        s = min(s + v, total)
        arc.append(s)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    return np.stack([np.interp(arc, cum, path[:, 0]), np.interp(arc, cum, path[:, 1])], axis=1)
