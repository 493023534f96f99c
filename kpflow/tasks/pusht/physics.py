"""Push-T physics in pymunk, built exactly as the standard env (Diffusion Policy's ``PushTEnv``) builds it.

What the standard env really simulates, and this module reproduces:

* No gravity and ``space.damping = 0``: pymunk scales velocities by ``damping ** dt`` each step, so a body keeps no
  velocity of its own and the block stops as soon as contact ends (quasi-static pushing).
* Four static wall segments of radius 2 from (5, 5) to (size - 6, size - 6).
* The agent: a kinematic circle of radius 15. Each of the 10 substeps of an action (dt = 0.01 s, 10 Hz control)
  sets ``v += (100 (target - p) + 20 (0 - v)) dt``, a critically damped PD tracker of the absolute target.
  Kinematic bodies ignore contact impulses, so the agent moves through the block and the walls alike.
* Frictionless contacts: the standard env writes ``body.friction = 1``, but pymunk bodies have no friction (only
  shapes do, default 0), so that line only adds a Python attribute. Shape friction stays 0 here too.
* The block: one body of mass 1 with the bar and the stem as two polygons. Two quirks of the standard env are the
  default (``physically_correct=False``): its centre of gravity is the plain mean of the two box centroids,
  (0, 45), instead of the area-weighted (0, 40.71); its moment of inertia is twice the bar's moment about the body
  origin (``inertia2`` reuses the bar's vertices). ``physically_correct=True`` gives a uniform T of mass 1:
  area-weighted centre of gravity and the moment about it.
"""

from __future__ import annotations

import numpy as np
import pymunk

from .geometry import AGENT_RADIUS, BAR, STEM
from .workspace import Workspace

SIM_HZ = 100
CONTROL_HZ = 10
SUBSTEPS = SIM_HZ // CONTROL_HZ
DT = 1.0 / SIM_HZ
KP, KV = 100.0, 20.0


def block_mass_properties(physically_correct: bool = False) -> tuple[float, tuple[float, float]]:
    """Moment of inertia and centre of gravity of the T (mass 1), standard quirks or physically correct."""
    if not physically_correct:
        moment = 2.0 * pymunk.moment_for_poly(1.0, BAR.tolist())
        return moment, (0.0, 45.0)  # mean of the centroids (0, 15) and (0, 75)
    areas = np.array([120.0 * 30.0, 30.0 * 90.0])
    masses = areas / areas.sum()
    cog = (masses[0] * BAR.mean(0) + masses[1] * STEM.mean(0)).tolist()
    offset = (-cog[0], -cog[1])
    moment = sum(pymunk.moment_for_poly(float(m), v.tolist(), offset) for m, v in zip(masses, (BAR, STEM)))
    return float(moment), (cog[0], cog[1])


class PushTPhysics:
    """One pymunk space with walls, the kinematic agent and the T block.

    :meth:`set_state` teleports the bodies (angle before position, because pymunk rotates a body about its centre
    of gravity) and :meth:`step` applies one absolute target for :data:`SUBSTEPS` substeps. The expert reuses one
    instance as a scratch simulator by resetting body states rather than copying the space.
    """

    def __init__(self, workspace: Workspace, physically_correct: bool = False):
        self.workspace = workspace
        self.space = pymunk.Space()
        self.space.gravity = (0.0, 0.0)
        self.space.damping = 0.0
        lo, hi = workspace.wall_lo, workspace.wall_hi
        corners = [(lo, hi), (lo, lo), (hi, lo), (hi, hi)]
        walls = [pymunk.Segment(self.space.static_body, a, b, 2) for a, b in zip(corners, corners[1:] + corners[:1])]

        self.agent = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        agent_shape = pymunk.Circle(self.agent, AGENT_RADIUS)

        moment, cog = block_mass_properties(physically_correct)
        self.block = pymunk.Body(1.0, moment)
        self.block_shapes = [pymunk.Poly(self.block, BAR.tolist()), pymunk.Poly(self.block, STEM.tolist())]
        self.block.center_of_gravity = cog
        self.space.add(*walls, self.agent, agent_shape, self.block, *self.block_shapes)

    # ----------------------------------------------------------------------------------------------- state
    def set_state(self, agent_pos, block_pose, agent_vel=(0.0, 0.0)) -> None:
        """Teleport the agent and the block; the block is at rest."""
        self.agent.position = (float(agent_pos[0]), float(agent_pos[1]))
        self.agent.velocity = (float(agent_vel[0]), float(agent_vel[1]))
        self.block.angle = float(block_pose[2])  # first: setting the angle rotates about the centre of gravity
        self.block.position = (float(block_pose[0]), float(block_pose[1]))
        self.block.velocity = (0.0, 0.0)
        self.block.angular_velocity = 0.0
        # pymunk keeps a contact-correction ("bias") velocity that Python cannot read; integrating the position over
        # dt = 0 clears it, so nothing of a previous state leaks into the next step.
        pymunk.Body.update_position(self.block, 0.0)

    @property
    def agent_pos(self) -> np.ndarray:
        return np.array(self.agent.position)

    @property
    def agent_vel(self) -> np.ndarray:
        return np.array(self.agent.velocity)

    @property
    def block_pose(self) -> np.ndarray:
        """``(x, y, theta)`` of the block's body origin; theta is not wrapped."""
        x, y = self.block.position
        return np.array([x, y, self.block.angle])

    # ----------------------------------------------------------------------------------------------- dynamics
    def step(self, target) -> None:
        """Track the absolute ``target`` for one control step (:data:`SUBSTEPS` physics steps of :data:`DT`).

        Same floating-point operations as the standard env: ``a = KP (target - p) + KV (0 - v)``, ``v += a dt``.
        """
        tx, ty = float(target[0]), float(target[1])
        agent, space = self.agent, self.space
        for _ in range(SUBSTEPS):
            (px, py), (vx, vy) = agent.position, agent.velocity
            agent.velocity = (
                vx + (KP * (tx - px) + KV * (0.0 - vx)) * DT,
                vy + (KP * (ty - py) + KV * (0.0 - vy)) * DT,
            )
            space.step(DT)
