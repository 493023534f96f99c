"""The task contract, and the named data that crosses layers.

Every task folder under ``kpflow/tasks/`` has the same files: ``env.py`` (the simulator), ``scene.py`` (what a scene
is and the seeded sampler for a condition and index), ``keypoints.py`` (observing the keypoints), ``demonstrator.py``
(the scripted demonstration and success with a failure reason) and ``task.py``, which puts them behind one class.
Closed-loop episodes talk to a :class:`~kpflow.core.policy.Policy` (whose layout a task declares,
:class:`~kpflow.core.policy.PolicyLayout`); the robosuite tasks (:class:`ArmTask`) transport one
recorded demonstration per scene, so their data is a :class:`~kpflow.trajectory.Trajectory` of end-effector poses and an
:class:`Execution` record of how the arm followed it.

The trial loop (:mod:`kpflow.eval.trials`) needs only this module's names: a new robosuite task implements
:class:`ArmTask` and a report (:mod:`kpflow.eval.reports`) that scores its trials.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from kpflow.trajectory import Keypoints, Trajectory

if TYPE_CHECKING:
    from kpflow.core.rollout import Episode

#: The evaluation stream's offset: scene ``i`` of a condition for run seed ``s`` is keyed ``(EVAL_SEED + s, c, i)``.
EVAL_SEED = 1_000_000


def scene_seed(seed: int, condition: int, index: int) -> int:
    """The reset seed of evaluation scene ``index`` of condition number ``condition`` (from 1) for run ``seed``: 32
    bits of numpy's ``SeedSequence((EVAL_SEED + seed, condition, index))``: a key of the same shape as Push-T's splits'
    ``(seed, split, i)`` and the robosuite tasks' ``(20_000 + seed, variant, i)``. Each run seed has its own stream (seed 1's scene 0 is not seed 0's scene 1), each
    condition its own, and none meets the small seeds collection draws demonstrations with (0, 1, 2, ...) but by a
    2^-32 chance."""
    return int(np.random.SeedSequence([EVAL_SEED + int(seed), int(condition), int(index)]).generate_state(1)[0])


@dataclass(frozen=True)
class EvaluationScene:
    """How an evaluation episode starts: the env's ``reset`` arguments (``{"seed": s}``, ``{"options": {...}}``), the
    seed the policy is reset with (its sampling noise) and what ``results.json`` records of the scene."""

    reset: dict
    policy_seed: int
    record: dict


@dataclass(frozen=True)
class Execution:
    """How a trajectory went on the arm: ``success`` and ``failure`` (None, or the first reason), the measured
    ``tip [T, 3]``, the ``tracking_error [T]`` (m), ``grasp_step`` (None if nothing was sealed), ``grasped`` (the
    object sealed first), ``collided`` and ``min_singular_value`` (of the arm's Jacobian, over the run)."""

    success: bool
    failure: str | None
    tip: np.ndarray
    tracking_error: np.ndarray
    grasp_step: int | None
    grasped: str | None
    collided: bool
    min_singular_value: float


@dataclass(frozen=True)
class Demonstration:
    """A recorded source demonstration: its ``scene``, what the task observed there before it (``observation``:
    the task's own record, e.g. the object box or the image), the commanded ``trajectory`` and its ``execution``."""

    scene: Any
    observation: Any
    trajectory: Trajectory
    execution: Execution


@dataclass(frozen=True)
class SegmentStart:
    """The scene when a segment of a demonstration begins, what carrying the segment depends on: ``poses`` (object or
    fixture -> (position [3], rotation [3, 3])), ``keypoints`` (the reference object's ``[N, 3]``, under its name:
    the object picked, or the goal of a place), the objects' ``yaws``, the ``gripper`` keypoint ``[1, 3]`` (the grip
    site), while an object is held its keypoints ``in_hand [S, M, 3]`` in the grip site's frame (in each of the
    ``S`` orders its symmetry allows, the one nearest the reference's first), and ``path_cost(positions [T, 3],
    rotations [T, 3, 3]) -> float``, how hard a path of the segment is for the arm from here (None: all alike)."""

    poses: dict[str, tuple[np.ndarray, np.ndarray]]
    keypoints: dict[str, np.ndarray]
    yaws: dict[str, float]
    gripper: np.ndarray
    in_hand: np.ndarray | None = None
    path_cost: Callable[[np.ndarray, np.ndarray], float] | None = None


@dataclass(frozen=True)
class Segment:
    """One object-centric segment of a recorded demonstration (``name``: ``"pick"``, ``"place"``): its commanded
    ``trajectory`` and the scene when it began (``start``)."""

    name: str
    trajectory: Trajectory
    start: SegmentStart


@dataclass
class TrialResult:
    """One trial of the evaluation grid: which ``condition``, scene ``index`` and ``variant`` (axis -> option, e.g.
    ``{"keypoints": "sift", "map": "gp"}``), the ``scene`` (as a dict), ``success``, ``failure`` and the report's
    ``scores``. ``artefacts`` (trajectory, execution, keypoints, images) stay in memory for figures."""

    condition: str
    index: int
    variant: dict[str, str]
    scene: dict
    success: bool
    failure: str | None
    scores: dict[str, Any]
    artefacts: dict[str, Any] = field(default_factory=dict, repr=False)

    def record(self) -> dict:
        """The JSON-ready row of ``results.json``."""
        return {"condition": self.condition, "index": self.index, **self.variant, "scene": self.scene,
                "success": self.success, "failure": self.failure, **self.scores}  # fmt: skip


#: the keypoint source that is the simulator's exact pairs (the upper bound for found correspondences)
ORACLE = "oracle"


class Task:
    """What every task is: a ``name`` and the ``conditions`` (scene distributions) an evaluation can ask for, the
    first the training one. Two kinds build on it: a :class:`GymTask` runs policies in closed loop (Push-T, the
    robosuite benchmark tasks, a task of your own), an :class:`ArmTask` transports one recorded demonstration per
    scene (packing, stacking). A task with neither (the frames task, whose scenes feed the map figures) declares
    only these."""

    name: str
    conditions: tuple[str, ...] = ("default",)

    @property
    def default_conditions(self) -> tuple[str, ...]:
        """The conditions an evaluation of ``all`` runs (every one, unless the task says otherwise)."""
        return tuple(self.conditions)

    def check_condition(self, condition: str) -> None:
        """Refuse a condition the task does not have, naming the ones it has."""
        if condition not in self.conditions:
            raise ValueError(f"{self.name} has no condition {condition!r}; choose from {', '.join(self.conditions)}")


class ArmTask(Task, abc.ABC):
    """A robosuite task solved zero-shot by transporting one demonstration (packing, stacking).

    ``conditions`` name the test conditions; ``keypoint_sources`` the ways the task can find keypoints (the
    evaluation grid's ``keypoints`` axis: a backbone name, ``"oracle"``, or the task's single ``"camera"``).
    """

    source_scene: Any
    #: the failure reason of a trial in which no keypoints were found (nothing is executed)
    no_keypoints = "no correspondences"

    @abc.abstractmethod
    def make_env(self):
        """A fresh simulator of this task (one per worker process)."""

    @abc.abstractmethod
    def sample_scene(self, condition: str, index: int, seed: int = 0):
        """Scene ``index`` of ``condition`` for ``seed`` (the same for every map and keypoint source)."""

    @abc.abstractmethod
    def demonstrate(self, env) -> Demonstration:
        """Run the scripted demonstrator in :attr:`source_scene` and record it."""

    @abc.abstractmethod
    def observe(self, env, scene, source: Demonstration, keypoint_source: Any) -> tuple[Keypoints | None, Any]:
        """Reset ``env`` to ``scene`` and find the keypoints that correspond to the source's (None when none were
        found), with the task's observation of the scene (what its report scores)."""

    @abc.abstractmethod
    def execute(self, env, trajectory: Trajectory, frames: list | None = None) -> Execution:
        """Run ``trajectory`` and say whether the task succeeded, and if not why (appending video frames)."""


class GymTask(Task, abc.ABC):
    """A task whose simulator is a Gymnasium env: what a new task implements, in a folder of its own, to be collected
    (``kpflow-collect``), trained on (``kpflow-train``), evaluated in closed loop (``kpflow-evaluate
    experiment=gym_policy``) and served (``kpflow-serve``); its YAML in a ``task/`` config folder names the class
    (docs/tutorials/own-task.md; ``kpflow-example reach_task DIR`` copies one).

    * :meth:`make_env` returns a ``gymnasium.Env`` whose ``reset(seed=i)`` draws scene ``i`` of ``condition``, whose
      observations are dicts holding ``keypoints [K, D]`` (:attr:`policy_layout`'s), and whose ``step(action [A])``
      reports ``info["is_success"]`` (Gymnasium's convention) and terminates once the task is done.
    * :attr:`policy_layout` (:class:`~kpflow.core.policy.PolicyLayout`): the keypoints, their named groups and the
      actions, which every learned or transporting policy is checked against.
    * :attr:`conditions`: the scene distributions an evaluation can ask for (the first is the training one);
      :attr:`max_steps`: the control steps an episode may take.
    * :meth:`expert`: a scripted :class:`~kpflow.core.policy.Policy` that solves the task (None when the task has
      none: its demonstrations then come from elsewhere, e.g. a LeRobot dataset).
    """

    max_steps: int = 200
    #: the info keys an episode records at every step for :meth:`score` (:attr:`~kpflow.core.rollout.Episode.tracked`)
    tracked: tuple[str, ...] = ()

    @property
    @abc.abstractmethod
    def policy_layout(self):
        """The :class:`~kpflow.core.policy.PolicyLayout` of the task's keypoints and actions."""

    @abc.abstractmethod
    def make_env(self, condition: str, render: bool = False):
        """A fresh ``gymnasium.Env`` drawing the scenes of ``condition`` (``render``: ``render()`` returns RGB frames)."""

    def expert(self):
        """A scripted policy that solves the task, or None."""
        return None

    def evaluation_scene(self, condition: str, index: int, seed: int) -> EvaluationScene:
        """Evaluation scene ``index`` of ``condition`` for run ``seed``: by default ``reset(seed=s)`` with ``s`` of
        the held-out stream (:func:`scene_seed`), the policy reset with ``s`` too."""
        s = scene_seed(seed, self.conditions.index(condition) + 1, index)
        return EvaluationScene({"seed": s}, s, {"seed": s})

    def steps_limit(self, condition: str, max_steps: int | None = None) -> int:
        """The control steps an episode of ``condition`` may take: ``max_steps``, else the task's."""
        return int(self.max_steps if max_steps is None else max_steps)

    def describe(self) -> dict:
        """What an evaluation's ``results.json`` records of the task's set-up besides its name (e.g. where its
        keypoints come from)."""
        return {}

    def score(self, episode: Episode) -> tuple[bool, str | None, dict]:
        """``(success, failure reason, scores)`` of an evaluation episode (:class:`~kpflow.core.rollout.Episode`):
        by default the env's success, ``"time limit"`` otherwise, and the steps and decisions taken."""
        return (
            episode.success,
            None if episode.success else "time limit",
            {"steps": episode.steps, "decisions": episode.decisions},
        )
