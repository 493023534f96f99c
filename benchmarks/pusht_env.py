"""Benchmark of kpflow's Push-T environment step against the standard gym-pusht step, single-threaded on the CPU.

Run::

    python benchmarks/pusht_env.py [--steps 6000] [--repeats 5] [--out PATH] [--profile]

The markdown tables are printed and written atomically to ``--out`` (default ``outputs/benchmarks/pusht_env.md``).

What is timed: ``env.step(action)`` only (resets are untimed), i.e. 10 physics substeps of the PD-driven agent, the
observation, the coverage, the reward and the info dict.

* kpflow: :class:`kpflow.tasks.pusht.PushTEnv` (observation = 25 keypoints + agent position + poses).
* baseline: gym-pusht 0.1.8's ``PushTEnv.step`` with ``obs_type="environment_state_agent_pos"``, transcribed below
  (:class:`GymPushTStep`) because gym-pusht itself pins ``pymunk<7`` and cannot be installed next to pymunk 7.
  The transcription keeps its code: the PD update in pymunk ``Vec2d`` arithmetic, 10 ``space.step`` calls, the
  post-solve collision handler counting contact points (pymunk 7's ``space.on_collision``), the coverage through
  ``pymunk_to_shapely`` (a fresh goal ``pymunk.Body`` and two ``MultiPolygon`` every step) and
  ``get_keypoints`` (the 8 vertices of the two boxes, ``v.rotated(angle) + position``) + agent position. Only
  rendering (pygame) is left out, which its ``step`` does not call for this observation type.

Workload: both envs replay the SAME recorded action sequence from the same states. Episodes of 300 steps start from
seeded in-distribution configurations (``make_split("in_distribution")``) whose goal is moved near the block
(offset ~N(0, 20 px), ~N(0, 0.3 rad)); the recorded policy aims at points that circle the block's centre
(radius 60-80 px) with noise, so the agent keeps pushing the block around near the goal and the coverage really
is computed (the table reports how often the bounding boxes overlap, i.e. shapely runs in kpflow's coverage).
Both simulations are built the same way (walls, kinematic agent, the T with the standard centre-of-gravity
quirk) and use the same floating-point operations, so the replayed trajectories agree; the table reports the
largest block-pose and coverage differences as a check.

Coverage share: the coverage of every visited state is timed on its own, on the same states, for each
implementation (kpflow: ``outline_coverage(to_world(pose, OUTLINE), goal_polygon)``; baseline: ``_get_coverage()``),
and divided by the step time.

Steps per second are medians over ``--repeats`` full replays (kpflow and baseline interleaved), after one untimed
warm-up replay each. Actions are float64 numpy arrays; a third row replays the baseline with the actions as Python
tuples (its PD update then stays in pymunk ``Vec2d`` arithmetic instead of mixing in numpy), to show how much of
its time is that conversion.
Everything runs on ONE thread (``OMP_NUM_THREADS=1`` before numpy is imported).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy is imported

import argparse
import cProfile
import datetime
import io
import platform
import pstats
import sys
import time
from pathlib import Path

import numpy as np
import pymunk
import shapely
import shapely.geometry as sg
from pymunk.vec2d import Vec2d

from kpflow.tasks.pusht import Config, PushTEnv, make_split
from kpflow.tasks.pusht.geometry import OUTLINE, outline_coverage, t_polygon, to_world
from kpflow.utils.io import write_text

EPISODE = 300  # steps between resets
SEED = 0

# ---------------------------------------------------------------------------------------------- baseline


def pymunk_to_shapely(body, shapes):
    """gym-pusht 0.1.8, verbatim."""
    geoms = []
    for shape in shapes:
        if isinstance(shape, pymunk.shapes.Poly):
            verts = [body.local_to_world(v) for v in shape.get_vertices()]
            verts += [verts[0]]
            geoms.append(sg.Polygon(verts))
        else:
            raise RuntimeError(f"Unsupported shape type {type(shape)}")
    geom = sg.MultiPolygon(geoms)
    return geom


class GymPushTStep:
    """gym-pusht 0.1.8's ``PushTEnv`` reduced to what ``step`` runs for ``obs_type="environment_state_agent_pos"``.

    Method bodies are the original's (pygame colours dropped); ``reset_to`` replaces its ``reset`` so that both
    benchmarked envs start from identical states: it rebuilds the space with ``_setup`` like ``reset`` does, but
    sets the block's angle before its position (kpflow's order; the original sets the position first, which
    places the body origin elsewhere because pymunk rotates about the centre of gravity). Resets are not timed.
    """

    def __init__(self):
        self.obs_type = "environment_state_agent_pos"
        self.k_p, self.k_v = 100, 20  # PD control.z
        self.control_hz = 10  # metadata["render_fps"]
        self.dt = 0.01
        self.block_cog = None
        self.damping = None
        self._last_action = None
        self.success_threshold = 0.95  # 95% coverage

    # ------------------------------------------------------------------------------------------ verbatim
    def _get_coverage(self):
        goal_body = self.get_goal_pose_body(self.goal_pose)
        goal_geom = pymunk_to_shapely(goal_body, self.block.shapes)
        block_geom = pymunk_to_shapely(self.block, self.block.shapes)
        intersection_area = goal_geom.intersection(block_geom).area
        goal_area = goal_geom.area
        return intersection_area / goal_area

    def step(self, action):
        self.n_contact_points = 0
        n_steps = int(1 / (self.dt * self.control_hz))
        self._last_action = action
        for _ in range(n_steps):
            # Step PD control
            # self.agent.velocity = self.k_p * (act - self.agent.position)    # P control works too.
            acceleration = self.k_p * (action - self.agent.position) + self.k_v * (Vec2d(0, 0) - self.agent.velocity)
            self.agent.velocity += acceleration * self.dt

            # Step physics
            self.space.step(self.dt)

        # Compute reward
        coverage = self._get_coverage()
        reward = np.clip(coverage / self.success_threshold, 0.0, 1.0)
        terminated = is_success = coverage > self.success_threshold

        observation = self.get_obs()
        info = self._get_info()
        info["is_success"] = is_success
        info["coverage"] = coverage

        truncated = False
        return observation, reward, terminated, truncated, info

    def get_obs(self):
        if self.obs_type == "environment_state_agent_pos":
            return {
                "environment_state": self.get_keypoints(self._block_shapes).flatten(),
                "agent_pos": np.array(self.agent.position),
            }
        raise NotImplementedError(self.obs_type)

    @staticmethod
    def get_goal_pose_body(pose):
        mass = 1
        inertia = pymunk.moment_for_box(mass, (50, 100))
        body = pymunk.Body(mass, inertia)
        # preserving the legacy assignment order for compatibility
        # the order here doesn't matter somehow, maybe because CoM is aligned with body origin
        body.position = pose[:2].tolist()
        body.angle = pose[2]
        return body

    def _get_info(self):
        n_steps = int(1 / self.dt * self.control_hz)
        n_contact_points_per_step = int(np.ceil(self.n_contact_points / n_steps))
        info = {
            "pos_agent": np.array(self.agent.position),
            "vel_agent": np.array(self.agent.velocity),
            "block_pose": np.array(list(self.block.position) + [self.block.angle]),
            "goal_pose": self.goal_pose,
            "n_contacts": n_contact_points_per_step,
        }
        return info

    def _handle_collision(self, arbiter, space, data):
        self.n_contact_points += len(arbiter.contact_point_set.points)

    def _setup(self):
        self.space = pymunk.Space()
        self.space.gravity = 0, 0
        self.space.damping = self.damping if self.damping is not None else 0.0
        self.teleop = False

        # Add walls
        walls = [
            self.add_segment(self.space, (5, 506), (5, 5), 2),
            self.add_segment(self.space, (5, 5), (506, 5), 2),
            self.add_segment(self.space, (506, 5), (506, 506), 2),
            self.add_segment(self.space, (5, 506), (506, 506), 2),
        ]
        self.space.add(*walls)

        # Add agent, block, and goal zone
        self.agent = self.add_circle(self.space, (256, 400), 15)
        self.block, self._block_shapes = self.add_tee(self.space, (256, 300), 0)
        self.goal_pose = np.array([256, 256, np.pi / 4])  # x, y, theta (in radians)
        if self.block_cog is not None:
            self.block.center_of_gravity = self.block_cog

        # Add collision handling (compatible with pymunk 7+)
        self.space.on_collision(0, 0, post_solve=self._handle_collision)
        self.n_contact_points = 0

    @staticmethod
    def add_segment(space, a, b, radius):
        shape = pymunk.Segment(space.static_body, a, b, radius)
        return shape

    @staticmethod
    def add_circle(space, position, radius):
        body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        body.position = position
        body.friction = 1
        shape = pymunk.Circle(body, radius)
        space.add(body, shape)
        return body

    @staticmethod
    def add_tee(space, position, angle, scale=30, color="LightSlateGray", mask=None):
        if mask is None:
            mask = pymunk.ShapeFilter.ALL_MASKS()
        mass = 1
        length = 4
        vertices1 = [
            (-length * scale / 2, scale),
            (length * scale / 2, scale),
            (length * scale / 2, 0),
            (-length * scale / 2, 0),
        ]
        inertia1 = pymunk.moment_for_poly(mass, vertices=vertices1)
        vertices2 = [
            (-scale / 2, scale),
            (-scale / 2, length * scale),
            (scale / 2, length * scale),
            (scale / 2, scale),
        ]
        inertia2 = pymunk.moment_for_poly(mass, vertices=vertices1)
        body = pymunk.Body(mass, inertia1 + inertia2)
        shape1 = pymunk.Poly(body, vertices1)
        shape2 = pymunk.Poly(body, vertices2)
        shape1.filter = pymunk.ShapeFilter(mask=mask)
        shape2.filter = pymunk.ShapeFilter(mask=mask)
        body.center_of_gravity = (shape1.center_of_gravity + shape2.center_of_gravity) / 2
        body.angle = angle
        body.position = position
        body.friction = 1
        space.add(body, shape1, shape2)
        return body, [shape1, shape2]

    @staticmethod
    def get_keypoints(block_shapes):
        """Get a (8, 2) numpy array with the T keypoints (the 4 vertices of each box)."""
        keypoints = []
        for shape in block_shapes:
            for v in shape.get_vertices():
                v = v.rotated(shape.body.angle)
                v = v + shape.body.position
                keypoints.append(np.array(v))
        return np.vstack(keypoints)  # np.row_stack in the original: an alias of np.vstack

    # ------------------------------------------------------------------------------------------ not verbatim
    def reset_to(self, config: Config):
        """Rebuild the space (as ``reset`` does) and set ``config``'s state, angle before position (see above)."""
        self._setup()
        self.goal_pose = np.array(config.goal_pose, float)
        self.agent.position = list(config.agent_pos)
        self.block.angle = config.block_pose[2]
        self.block.position = list(config.block_pose[:2])
        self.space.step(self.dt)  # "Run physics to take effect", as its _set_state

    def set_block_pose(self, pose):
        """Teleport the block (for timing the coverage alone on recorded states)."""
        self.block.angle = float(pose[2])
        self.block.position = (float(pose[0]), float(pose[1]))


# ---------------------------------------------------------------------------------------------- workload


def make_configs(n_episodes: int, seed: int) -> list[Config]:
    """In-distribution configurations with the goal moved near the block."""
    rng = np.random.default_rng(seed)
    out = []
    for c in make_split("in_distribution", n_episodes, seed=seed):
        goal = np.array(c.block_pose) + (*rng.normal(0.0, 20.0, 2), rng.normal(0.0, 0.3))
        out.append(Config(c.agent_pos, c.block_pose, tuple(float(v) for v in goal), "standard"))
    return out


def record_actions(configs: list[Config], steps: int, seed: int) -> list[np.ndarray]:
    """The action sequence (one [EPISODE, 2] array per episode): targets circling the block with noise."""
    rng = np.random.default_rng(seed + 1)
    env = PushTEnv()
    episodes, left = [], steps
    for config in configs:
        n = min(EPISODE, left)
        if n <= 0:
            break
        obs, _ = env.reset(options={"config": config})
        phase, speed, radius = (
            rng.uniform(0, 2 * np.pi),
            rng.choice([-1.0, 1.0]) * rng.uniform(0.15, 0.3),
            rng.uniform(60, 80),
        )
        actions = np.empty((n, 2))
        for k in range(n):
            centre = obs["keypoints"][:12].mean(0)
            phase += speed
            a = centre + radius * np.array([np.cos(phase), np.sin(phase)]) + rng.normal(0.0, 8.0, 2)
            actions[k] = np.clip(a, 0.0, 512.0)
            obs, *_ = env.step(actions[k])
        episodes.append(actions)
        left -= n
    return episodes


def replay_kpflow(configs, episodes, record: bool = False):
    """Seconds spent in ``step`` over the whole sequence (and, when ``record``, poses and coverages).

    One env for all episodes, reset to each configuration (untimed) as an evaluation loop would.
    """
    env = PushTEnv()
    total, poses, covs = 0.0, [], []
    clock = time.perf_counter
    for config, actions in zip(configs, episodes):
        env.reset(options={"config": config})
        step = env.step
        if record:
            for a in actions:
                obs, _, _, _, info = step(a)
                poses.append(env.physics.block_pose)
                covs.append(info["coverage"])
            continue
        t0 = clock()
        for a in actions:
            step(a)
        total += clock() - t0
    return total, np.array(poses), np.array(covs)


def replay_baseline(configs, episodes, record: bool = False, as_tuples: bool = False):
    """As :func:`replay_kpflow`; ``as_tuples`` passes each action as a Python tuple instead of a numpy array."""
    env = GymPushTStep()
    if as_tuples:
        episodes = [[(float(x), float(y)) for x, y in actions] for actions in episodes]
    total, poses, covs = 0.0, [], []
    clock = time.perf_counter
    for config, actions in zip(configs, episodes):
        env.reset_to(config)
        step = env.step
        if record:
            for a in actions:
                _, _, _, _, info = step(a)
                poses.append(info["block_pose"])
                covs.append(info["coverage"])
            continue
        t0 = clock()
        for a in actions:
            step(a)
        total += clock() - t0
    return total, np.array(poses), np.array(covs)


def time_coverage(configs, episodes, poses):
    """Seconds to compute the coverage of every recorded state, kpflow's way and the baseline's way."""
    goals = np.concatenate([np.repeat(np.array(c.goal_pose)[None], len(a), 0) for c, a in zip(configs, episodes)])
    # kpflow: the goal polygon is built once per reset (as the env does); per step, the outline + coverage
    polygons = {}
    goal_polys = [polygons.setdefault(tuple(g), t_polygon(g)) for g in goals]
    clock = time.perf_counter
    t0 = clock()
    k_cov = [outline_coverage(to_world(p, OUTLINE), gp) for p, gp in zip(poses, goal_polys)]
    t_kpflow = clock() - t0
    base = GymPushTStep()
    base.reset_to(configs[0])
    t_base, b_cov = 0.0, []
    for p, g in zip(poses, goals):
        base.goal_pose = g
        base.set_block_pose(p)
        t0 = clock()
        b_cov.append(base._get_coverage())
        t_base += clock() - t0
    return t_kpflow, t_base, np.array(k_cov), np.array(b_cov)


def profile_kpflow(configs, episodes) -> str:
    pr = cProfile.Profile()
    pr.enable()
    replay_kpflow(configs, episodes)
    pr.disable()
    buf = io.StringIO()
    pstats.Stats(pr, stream=buf).sort_stats("tottime").print_stats(15)
    return f"cProfile of one kpflow replay, sorted by own time:\n\n```\n{buf.getvalue().strip()}\n```"


# ---------------------------------------------------------------------------------------------- main


def table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--steps", type=int, default=6000, help="environment steps per replay (default 6000)")
    ap.add_argument("--repeats", type=int, default=5, help="timed replays per env (default 5); medians are reported")
    ap.add_argument("--out", type=Path, default=Path("outputs/benchmarks/pusht_env.md"), help="markdown output file")
    ap.add_argument("--profile", action="store_true", help="append a cProfile of one kpflow replay")
    args = ap.parse_args(argv)
    if args.steps < 1 or args.repeats < 1:
        ap.error("--steps and --repeats must be >= 1")

    t_start, load_start = time.perf_counter(), os.getloadavg()[0]

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t_start:6.1f} s] {msg}", file=sys.stderr, flush=True)

    n_episodes = -(-args.steps // EPISODE)
    configs = make_configs(n_episodes, SEED)
    log(f"recording {args.steps} actions in {n_episodes} episodes")
    episodes = record_actions(configs, args.steps, SEED)
    n_steps = sum(len(a) for a in episodes)

    # check: the two replays follow the same trajectory (untimed)
    _, k_poses, k_cov = replay_kpflow(configs, episodes, record=True)
    _, b_poses, b_cov = replay_baseline(configs, episodes, record=True)
    pose_diff = float(np.abs(k_poses[:, :2] - b_poses[:, :2]).max())
    angle_diff = float(np.abs(k_poses[:, 2] - b_poses[:, 2]).max())
    cov_diff = float(np.abs(k_cov - b_cov).max())
    overlap = float(np.mean([
        shapely.intersects(t_polygon(p).envelope, t_polygon(c.goal_pose).envelope)
        for p, c in zip(k_poses, (c for c, a in zip(configs, episodes) for _ in a))
    ]))  # fmt: skip
    log(f"replays agree to {pose_diff:.2e} px / {angle_diff:.2e} rad / coverage {cov_diff:.2e}")

    replay_kpflow(configs, episodes), replay_baseline(configs, episodes)  # warm-up
    replay_baseline(configs, episodes, as_tuples=True)
    k_times, b_times, bt_times = [], [], []
    for r in range(args.repeats):
        k_times.append(replay_kpflow(configs, episodes)[0])
        b_times.append(replay_baseline(configs, episodes)[0])
        bt_times.append(replay_baseline(configs, episodes, as_tuples=True)[0])
        log(
            f"repeat {r + 1}/{args.repeats}: kpflow {n_steps / k_times[-1]:.0f} steps/s, baseline "
            f"{n_steps / b_times[-1]:.0f} steps/s (tuple actions {n_steps / bt_times[-1]:.0f})"
        )
    kc_times, bc_times = [], []
    for _ in range(args.repeats):
        tk, tb, kc, bc = time_coverage(configs, episodes, k_poses)
        kc_times.append(tk), bc_times.append(tb)
    cov_same = float(np.abs(kc - bc).max())  # the two coverage functions on the same states

    k_step, b_step = float(np.median(k_times)) / n_steps, float(np.median(b_times)) / n_steps
    bt_step = float(np.median(bt_times)) / n_steps
    k_cov_t, b_cov_t = float(np.median(kc_times)) / n_steps, float(np.median(bc_times)) / n_steps
    rows = [
        [
            "kpflow `PushTEnv.step` (25 keypoints + poses + coverage + info)",
            f"{1 / k_step:,.0f}",
            f"{k_step * 1e6:.1f}",
            f"{k_cov_t * 1e6:.1f}",
            f"{k_cov_t / k_step:.0%}",
            f"{b_step / k_step:.2f}x",
        ],
        [
            "baseline: gym-pusht 0.1.8 `step` (transcribed; 8 keypoints + agent pos)",
            f"{1 / b_step:,.0f}",
            f"{b_step * 1e6:.1f}",
            f"{b_cov_t * 1e6:.1f}",
            f"{b_cov_t / b_step:.0%}",
            "1 (reference)",
        ],
        [
            "baseline, actions passed as Python tuples instead of numpy arrays",
            f"{1 / bt_step:,.0f}",
            f"{bt_step * 1e6:.1f}",
            f"{b_cov_t * 1e6:.1f}",
            f"{b_cov_t / bt_step:.0%}",
            f"{b_step / bt_step:.2f}x",
        ],
    ]
    header = [
        "step",
        "steps/s (median)",
        "us / step",
        "coverage us / step",
        "coverage share of step",
        "speed-up vs baseline",
    ]
    load_end = os.getloadavg()[0]
    verdict = "PASS" if b_step / k_step >= 2.0 else "MISS"
    text = "\n\n".join(
        [
            f"# Push-T environment step benchmark\n\n{datetime.datetime.now().isoformat(timespec='seconds')}; "
            f"{platform.processor() or platform.machine()}, Python {platform.python_version()}, pymunk {pymunk.version}, "
            f"shapely {shapely.__version__}, numpy {np.__version__}; OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}. "
            f"{n_steps} steps per replay ({len(episodes)} episodes of <= {EPISODE} steps, in-distribution starts with the "
            f"goal near the block), median over {args.repeats} replays after one warm-up; resets untimed.",
            table(header, rows),
            f"- target: kpflow >= 2x the baseline's steps/s: **{verdict}** ({b_step / k_step:.2f}x)\n"
            f"- same trajectories: largest block-pose difference between the two replays {pose_diff:.1e} px, "
            f"{angle_diff:.1e} rad; largest coverage difference {cov_diff:.1e} (on identical states: {cov_same:.1e})\n"
            f"- coverage work: the block's and the goal's bounding boxes overlap (shapely runs in kpflow) on "
            f"{overlap:.0%} of the steps; mean coverage {k_cov.mean():.2f}, coverage > 0 on {np.mean(k_cov > 0):.0%}\n"
            f"- per-repeat steps/s, kpflow: {', '.join(f'{n_steps / t:,.0f}' for t in k_times)}; baseline: "
            f"{', '.join(f'{n_steps / t:,.0f}' for t in b_times)}; baseline with tuple actions: "
            f"{', '.join(f'{n_steps / t:,.0f}' for t in bt_times)}\n"
            f"- actions are float64 numpy arrays [2] for kpflow and the baseline's main row (gym's usual type); the "
            f"baseline's PD update then mixes numpy and pymunk ``Vec2d`` arithmetic, which the tuple row avoids",
        ]
    )
    if args.profile:
        log("profile")
        text += "\n\n## where kpflow's step spends its time\n\n" + profile_kpflow(configs, episodes)
    text += (
        f"\n\n_total run time {time.perf_counter() - t_start:.0f} s; 1-min load average {load_start:.2f} at start, "
        f"{load_end:.2f} at end on {os.cpu_count()} CPUs (above ~1 means other processes shared the CPUs and "
        f"timings are noisier)_\n"
    )
    print(text)
    write_text(args.out, text)
    log(f"wrote {args.out}")


if __name__ == "__main__":
    main()
