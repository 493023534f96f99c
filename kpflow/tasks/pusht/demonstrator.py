"""A scripted Push-T demonstrator: simulated candidate pushes, routes around the block, hand-like motion.

At each decision the expert lists candidate pushes -- a contact point on the T's outline, a push direction (the
inward normal turned by up to 35 degrees) and a push length -- and scores each by simulating it exactly in one
scratch copy of the physics (:class:`PushTPhysics`, reset by body states). The score is the mean distance of the
block's 12 keypoints to the goal's after the push, plus a small charge per pixel of travel. The best push that
improves on the current pose is executed: route to a point behind the contact along the visibility-graph shortest
path around the T padded by the agent radius, smoothed, then push along a straight line. Targets move like a hand
on a mouse: speed at most ``max_speed`` px per step, bounded acceleration, the approach slowing to a gentle entry
speed instead of stopping, and a per-episode random speed and route wobble so demonstrations vary.

While executing, the expert watches the block: if it strays from the simulated prediction (or moves while the
agent is only travelling) the plan is dropped and a new decision is made.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely

from .geometry import AGENT_RADIUS, OUTLINE, T_KEYPOINTS, to_world
from .physics import DT, KP, KV, SUBSTEPS, PushTPhysics
from .routing import padded_obstacle, retime, shortest_path, smooth
from .workspace import Workspace, get_workspace

ANGLES = np.deg2rad([-35.0, 0.0, 35.0])
ENTRY_SPEED = 3.0  # px per step when the agent reaches the push line
BACKOFF = 20.0  # the push line starts this far behind the contact point
ROUTE_PAD = AGENT_RADIUS + 6.0
MAX_ROUTE_TRIES = 12  # candidates, best first, tried for a route before giving up on a decision


def _contacts(spacing: float = 15.0) -> tuple[np.ndarray, np.ndarray]:
    """Contact points on the T outline and their outward normals, in body coordinates.

    Points sit along each edge at most ``spacing`` apart (not at the two concave corners, which a disc of radius
    15 cannot reach); the six convex corners get the bisector of their edges' normals.
    """
    poly = shapely.Polygon(OUTLINE)
    n = len(OUTLINE)
    normals = []
    for i in range(n):
        e = OUTLINE[(i + 1) % n] - OUTLINE[i]
        nrm = np.array([e[1], -e[0]]) / np.linalg.norm(e)
        mid = OUTLINE[i] + 0.5 * e
        if poly.contains(shapely.Point(mid + 1e-3 * nrm)):
            nrm = -nrm
        normals.append(nrm)
    points, out = [], []
    for i in range(n):
        a, b = OUTLINE[i], OUTLINE[(i + 1) % n]
        k = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
        for t in (np.arange(k) + 0.5) / k:
            points.append(a + t * (b - a))
            out.append(normals[i])
        bisector = normals[i - 1] + normals[i]
        if poly.contains(shapely.Point(a - 1e-3 * bisector)):  # convex corner
            points.append(a)
            out.append(bisector / np.linalg.norm(bisector))
    return np.array(points), np.array(out)


CONTACTS, NORMALS = _contacts()


def keypoint_cost(pose, goal_keypoints: np.ndarray) -> float:
    """Mean distance (px) between the block's keypoints at ``pose`` and the goal's."""
    return float(np.linalg.norm(to_world(pose, T_KEYPOINTS) - goal_keypoints, axis=-1).mean())


@dataclass
class Plan:
    """Targets to execute, the block poses the simulation predicts after each, and the push's score."""

    targets: list = field(default_factory=list)
    predicted: list = field(default_factory=list)  # None while travelling (the block must not move)
    cost: float = np.inf
    entry: np.ndarray | None = None  # where the push line starts, and its direction
    direction: np.ndarray | None = None


class PushTExpert:
    """Scripted demonstrator with the policy interface ``reset(seed)`` / ``act(obs) -> target``.

    Args:
        workspace: ``"standard"``, ``"large"`` or a :class:`Workspace`; must match the env's.
        max_speed: bound on the target's motion per step (px); the per-episode cruise speed is drawn in
            [0.6, 1.0] x ``max_speed``.
        travel_cost: score charge per pixel of travel (trades a slightly worse push for a much shorter trip).
        physically_correct: use the same mass properties as the env.
    """

    def __init__(
        self,
        workspace: str | Workspace = "standard",
        max_speed: float = 15.0,
        push_speed: float = 8.0,
        accel: float = 2.5,
        travel_cost: float = 0.01,
        physically_correct: bool = False,
        seed: int | None = None,
    ):
        if not 0 < push_speed <= max_speed:
            raise ValueError(f"need 0 < push_speed <= max_speed, got {push_speed} and {max_speed}")
        self.workspace = get_workspace(workspace)
        self.max_speed, self.push_speed, self.accel = float(max_speed), float(push_speed), float(accel)
        self.travel_cost = float(travel_cost)
        self.sim = PushTPhysics(self.workspace, physically_correct)
        self.reset(seed)

    def reset(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)
        self.cruise = self.max_speed * self.rng.uniform(0.6, 1.0)
        self.plan = Plan()
        self._agent_pos, self._agent_vel = None, np.zeros(2)
        self._last_target = None
        self._expected = None  # (block pose expected after the last target, tolerance in px)
        self._stalls = 0

    # ------------------------------------------------------------------------------------------------ acting
    def act(self, obs: dict) -> np.ndarray:
        """The next absolute target for the agent, given an observation of :class:`PushTEnv`."""
        agent, block, goal = (np.asarray(obs[k], float) for k in ("agent_pos", "block_pose", "goal_pose"))
        self._track_agent(agent)
        if self.plan.targets and self._expected is not None:
            reference, tolerance = self._expected
            if keypoint_cost(block, to_world(reference, T_KEYPOINTS)) > tolerance:
                self.plan = Plan()
        if not self.plan.targets:
            self.plan = self._decide(agent, block, goal)
        if not self.plan.targets:  # nothing to do: hold
            target, self._expected = agent.copy(), None
        else:
            target = self.plan.targets.pop(0)
            predicted = self.plan.predicted.pop(0)
            self._expected = (block, 0.5) if predicted is None else (predicted, 3.0)
        target = self._limit(agent, np.clip(target, 0.0, self.workspace.size))
        self._last_target = target
        return target

    def _limit(self, agent: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Keep the target within ``max_speed`` of the previous one (the bound holds whatever the plan says)."""
        prev = agent if self._last_target is None else self._last_target
        step = target - prev
        norm = np.linalg.norm(step)
        return prev + step * (self.max_speed / norm) if norm > self.max_speed else target

    def _track_agent(self, agent: np.ndarray) -> None:
        """Agent velocity from the known PD law and the last target (observations carry positions only)."""
        if self._last_target is None or self._agent_pos is None:
            self._agent_pos, self._agent_vel = agent, np.zeros(2)
            return
        p, v = self._agent_pos, self._agent_vel
        for _ in range(SUBSTEPS):
            v = v + (KP * (self._last_target - p) + KV * (0.0 - v)) * DT
            p = p + v * DT
        self._agent_pos, self._agent_vel = agent, v

    # ------------------------------------------------------------------------------------------------ planning
    def _decide(self, agent: np.ndarray, block: np.ndarray, goal: np.ndarray) -> Plan:
        goal_kp = to_world(goal, T_KEYPOINTS)
        now = keypoint_cost(block, goal_kp)
        outline = to_world(block, OUTLINE)
        obstacle = padded_obstacle(outline, AGENT_RADIUS + 2.0)
        route_obstacle = padded_obstacle(outline, ROUTE_PAD)
        lengths = np.unique(np.clip(np.array([0.15, 0.4, 1.0]) * 1.2 * now, 1.0, 120.0).round(1))
        if self._stalls:
            lengths = np.unique(np.concatenate([lengths, self.rng.uniform(1.0, 60.0, 2).round(1)]))
        c, s = np.cos(block[2]), np.sin(block[2])
        rot = np.array([[c, -s], [s, c]])
        points, normals = CONTACTS @ rot.T + block[:2], NORMALS @ rot.T

        candidates = []  # (score, index, Plan) of every push that improves on the current pose
        lo, hi = 0.0, float(self.workspace.size)
        for point, normal in zip(points, normals):
            for angle in ANGLES:
                ca, sa = np.cos(angle), np.sin(angle)
                d = -np.array([ca * normal[0] - sa * normal[1], sa * normal[0] + ca * normal[1]])
                entry = point - d * (AGENT_RADIUS + BACKOFF)
                if np.any(entry < lo) or np.any(entry > hi):
                    continue
                touch = point - d * (AGENT_RADIUS + 1.0)
                if shapely.intersects(shapely.LineString([entry, touch]), obstacle.buffer(-1.5)):
                    continue  # the straight push line runs into another part of the T
                charge = self.travel_cost * float(np.linalg.norm(entry - agent))
                for length in lengths:
                    end = point + d * (length - AGENT_RADIUS)
                    targets = retime(np.stack([entry, end]), self.push_speed, self.accel, ENTRY_SPEED, 0.0)
                    targets = np.concatenate([targets, targets[-1:], targets[-1:]])  # settle
                    poses = self._simulate(entry, d, block, targets)
                    after = keypoint_cost(poses[-1], goal_kp)
                    if after < now - 0.02:
                        plan = Plan(list(targets), list(poses), after + charge, entry, d)
                        candidates.append((plan.cost, len(candidates), plan))
        # The best push whose entry the agent can reach (a block against a wall hides some entries).
        for _, _, best in sorted(candidates, key=lambda c: c[:2])[:MAX_ROUTE_TRIES]:
            route = self._route(agent, best.entry, best.direction, route_obstacle)
            if route is not None:
                self._stalls = 0
                v0 = float(np.linalg.norm(self._agent_vel)) * DT * SUBSTEPS
                approach = retime(route, self.cruise, self.accel, v0, ENTRY_SPEED)
                return Plan(list(approach) + best.targets, [None] * len(approach) + best.predicted, best.cost)
        self._stalls += 1
        return self._wander(agent, route_obstacle) if self._stalls > 1 else Plan()

    def _simulate(self, entry: np.ndarray, d: np.ndarray, block: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """Block poses after each target, starting from the steady state of tracking the entry speed along ``d``."""
        speed = ENTRY_SPEED / (DT * SUBSTEPS)  # px/s
        self.sim.set_state(entry - d * 0.2 * speed, block, agent_vel=d * speed)  # critically damped lag: 2 zeta/w v
        poses = np.empty((len(targets), 3))
        for k, target in enumerate(targets):
            self.sim.step(target)
            poses[k] = self.sim.block_pose
        return poses

    def _route(self, agent: np.ndarray, entry: np.ndarray, d: np.ndarray, obstacle) -> np.ndarray | None:
        """Path from the agent to ``entry``, arriving along ``d`` over the last ``BACKOFF`` px when there is room."""
        bounds = (0.0, float(self.workspace.size))
        lead = entry - d * BACKOFF
        via = lead if not shapely.intersects(shapely.LineString([lead, entry]), obstacle) else entry
        start = [agent]
        if shapely.intersects(shapely.Point(agent), obstacle):  # touching the block after a push: back off first
            start.append(self._escape(agent, obstacle))
        path = shortest_path(start[-1], via, obstacle, bounds)
        if path is None:
            return None
        path = np.concatenate([np.array(start[:-1]).reshape(-1, 2), path])
        wobble = self.rng.normal(0.0, 8.0, size=path[1:-1].shape)
        moved = path.copy()
        moved[1:-1] += wobble
        if not shapely.intersects(shapely.LineString(moved), obstacle):
            path = moved
        path = smooth(path, obstacle)
        if via is not entry:
            path = np.concatenate([path, entry[None]])
        return path

    @staticmethod
    def _escape(agent: np.ndarray, obstacle) -> np.ndarray:
        """The nearest point 1 px outside ``obstacle``, straight away from its boundary."""
        near = np.asarray(shapely.shortest_line(shapely.Point(agent), obstacle.exterior).coords[1])
        away = near - agent
        norm = np.linalg.norm(away)
        return near + (away / norm if norm > 1e-9 else np.array([0.0, -1.0]))

    def _wander(self, agent: np.ndarray, obstacle) -> Plan:
        """No push helps: move to a random free spot nearby so the next decision starts elsewhere."""
        start = self._escape(agent, obstacle) if shapely.intersects(shapely.Point(agent), obstacle) else agent
        for _ in range(20):
            spot = start + self.rng.normal(0.0, 60.0, 2)
            spot = np.clip(spot, 20.0, self.workspace.size - 20.0)
            path = shortest_path(start, spot, obstacle, (0.0, float(self.workspace.size)))
            if path is not None:
                path = np.concatenate([agent[None], path]) if start is not agent else path
                targets = retime(path, self.cruise, self.accel)
                return Plan(list(targets), [None] * len(targets))
        return Plan()
