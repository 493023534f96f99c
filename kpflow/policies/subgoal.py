"""A goal within reach and turn: a policy is shown its goal no farther from the object than ``reach`` and turned from
it by no more than ``turn_deg``, on the way to the real one.

A policy learned from demonstrations has seen the goal only so far from the object (in the Push-T Table 1 store,
centroids 379 px apart at the 99th percentile of its chunks), while Push-T's object-OOD split starts the block up
to 953 px from the goal (median 494 px). Before the wrapped policy acts, the observation's goal keypoints ``g_j``
are translated towards the object, keeping the goal's orientation:

    g_j' = g_j + (min(1, r / |c_g - c_o|) - 1) (c_g - c_o),

with ``c_o`` and ``c_g`` the centroids of the object's and the goal's keypoints in the current observation and ``r``
the reach: the subgoal's centroid lies ``r`` from the object's on the line to the goal's. As the object comes within
``r`` of the goal the subgoal is the goal, and the policy acts exactly as it would unwrapped.

The same holds for the goal's turn (planar keypoints, the goal's keypoints in the object's order). Demonstrations
bring the object to its goal turned by little (Push-T Table 1 store: within 10 px of the goal, 99 % of chunks are
turned by less than 49 degrees) while a scene can leave it near the goal turned half round, where a learned policy
has seen nothing to do and waits. With a turn limit ``a``, the goal is first turned about its centroid so that the
object needs at most ``a`` to match it:

    g_j' = c_g + R(clip(theta, -a, a) - theta) (g_j - c_g),
    theta = atan2(sum_j (o_j - c_o) x (g_j - c_g), sum_j (o_j - c_o) . (g_j - c_g)),

``theta`` being the rotation that best carries the object's centred keypoints ``o_j`` onto the goal's (the 2-D
rigid fit's angle, :func:`kpflow.geometry.alignment.planar_turn`). As the object turns the subgoal turns on ahead of it until the goal is within ``a``. With an
observation history, every frame's goal is moved by the current frame's turn and translation (the goal does not
move in an episode).

The wrapped policy's actions are checked as every K-CFM policy's are (:func:`~kpflow.policies.checks.check_actions`):
NaN or inf is refused, not returned.
"""

from __future__ import annotations

import numpy as np

from kpflow.core.policy import Policy

from ..geometry.alignment import planar_turn
from ..geometry.angles import planar_rotation
from ..maps.validation import check_positive
from .checks import check_actions


def subgoal_shift(keypoints: np.ndarray, object: tuple[int, ...], goal: tuple[int, ...], reach: float) -> np.ndarray:
    """The translation ``[D]`` that brings the goal of one observation ``keypoints [K, D]`` to within ``reach`` of its
    object (zero when it is already): ``(min(1, r / |c_g - c_o|) - 1) (c_g - c_o)`` (module docstring)."""
    kp = np.asarray(keypoints, dtype=np.float64)
    delta = kp[list(goal)].mean(0) - kp[list(object)].mean(0)
    distance = float(np.linalg.norm(delta))
    return (reach / distance - 1.0) * delta if distance > reach else np.zeros_like(delta)


def subgoal_turn(keypoints: np.ndarray, object: tuple[int, ...], goal: tuple[int, ...], turn: float) -> float:
    """The angle (radians) by which to turn the goal of planar ``keypoints [K, 2]`` about its centroid so that its
    object needs at most ``turn`` radians to match it: ``clip(theta, -turn, turn) - theta`` (module docstring)."""
    kp = np.asarray(keypoints, dtype=np.float64)
    theta = planar_turn(kp[list(object)], kp[list(goal)])
    return float(np.clip(theta, -turn, turn) - theta)


class SubgoalPolicy:
    """``policy`` acting on observations whose goal is turned to within ``turn_deg`` of the object
    (:func:`subgoal_turn`) and moved to within ``reach`` of it (:func:`subgoal_shift`).

    Args:
        policy: the wrapped policy; it receives ``obs`` with ``"keypoints"`` (and ``"keypoints_history"`` when
            present) replaced, and nothing else changed.
        object: indices of the object's keypoints in an observation ``[K, D]``.
        goal: indices of the goal's keypoints, in the object's order when ``turn_deg`` is given.
        reach: the largest object-goal centroid distance the policy is shown (> 0, observation units: px in Push-T);
            None: any.
        turn_deg: the largest object-goal turn the policy is shown (degrees, > 0; planar keypoints only); None: any.
    """

    def __init__(self, policy: Policy, object: tuple[int, ...], goal: tuple[int, ...], reach: float | None = None,
                 turn_deg: float | None = None) -> None:  # fmt: skip
        check_positive("reach", reach, optional=True, what=" (the largest object-goal distance shown)")
        check_positive("turn_deg", turn_deg, optional=True, what=" (the largest object-goal turn shown, degrees)")
        self.reach = None if reach is None else float(reach)
        self.turn_deg = None if turn_deg is None else float(turn_deg)
        if not object or not goal or set(object) & set(goal):
            raise ValueError(f"object and goal need >= 1 keypoint each and none in common; got {object} and {goal}")
        if self.turn_deg is not None and len(object) != len(goal):
            raise ValueError(
                f"turn_deg needs the goal's keypoints in the object's order; got {len(object)} and {len(goal)}"
            )
        self.policy, self.object, self.goal = policy, tuple(object), tuple(goal)
        self.n_obs = int(getattr(policy, "n_obs", 1))  # the observation history the rollout must hand over
        self.execute = getattr(policy, "execute", None)

    def reset(self, seed: int | None = None) -> None:
        self.policy.reset(seed)

    def shown(self, obs: dict) -> dict:
        """``obs`` with every frame's goal turned and moved as the current frame's needs (module docstring).

        Raises ``ValueError`` for keypoints that hold NaN or inf, or that are so large that moving the goal overflows.
        """
        frames = {key: np.array(obs[key], dtype=np.float64) for key in ("keypoints", "keypoints_history") if key in obs}
        for key, kp in frames.items():
            if not np.isfinite(kp).all():
                raise ValueError(f"obs[{key!r}] holds {int((~np.isfinite(kp)).sum())} NaN or inf value(s)")
        current = (frames["keypoints"] if "keypoints" in frames else frames["keypoints_history"][-1]).copy()
        goal = list(self.goal)
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow is refused below, naming the observation
            centre, rotation = current[goal].mean(0), None
            if self.turn_deg is not None:
                if current.shape[-1] != 2:
                    raise ValueError(f"turn_deg applies to planar keypoints; got {current.shape[-1]}-D ones")
                a = subgoal_turn(current, self.object, self.goal, np.radians(self.turn_deg))
                rotation = planar_rotation(a)
                current[goal] = centre + (current[goal] - centre) @ rotation.T  # the shift is read off the turned goal
            shift = (
                np.zeros(current.shape[-1])
                if self.reach is None
                else subgoal_shift(current, self.object, self.goal, self.reach)
            )
            for kp in frames.values():
                if rotation is not None:
                    kp[..., goal, :] = centre + (kp[..., goal, :] - centre) @ rotation.T
                kp[..., goal, :] += shift
        for key, kp in frames.items():
            if not np.isfinite(kp).all():
                largest = np.abs(np.asarray(obs[key], dtype=np.float64)).max()
                raise ValueError(
                    f"obs[{key!r}] is too large to move its goal within reach and turn: it overflowed (largest coordinate {largest:.4g})"
                )
        return {**obs, **frames}

    def act(self, obs: dict) -> np.ndarray:
        """The wrapped policy's chunk for ``obs`` with its goal within reach and turn (:meth:`shown`); ``ValueError`` if it
        holds NaN or inf."""
        return check_actions(self.policy.act(self.shown(obs)), "the policy within reach and turn")
