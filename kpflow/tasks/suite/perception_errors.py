"""How far a perception's keypoints are from the simulator's along a closed-loop episode, stage by stage: where a
policy on camera keypoints loses its precision.

A :class:`~.gym_env.SuiteGymEnv` whose objects are read by cameras compares, at every read, what the policy is shown
with what the simulator knows, and sorts each comparison into the stage it belongs to:

* ``pick``: the object to pick, read before the jaws close on it (with a pose filter: its estimate, lag included);
* ``grasp``: the object to pick as the policy last saw it, at the step the jaws close (what the grasp was aimed at);
* ``held``: the object in the jaws, carried with them from where it was last seen (the hand hides it);
* ``goal``: the target's keypoints (the peg, the cube to stack on, the bin), at every read;
* ``place``: at the step the jaws open, the held object's keypoints *relative to the target's centre* as the policy
  saw them against the simulator's (what an insertion depends on: a bias shared by both objects cancels).

The error of one comparison is the largest distance (mm) between an object's perceived keypoints and its true ones,
both ordered by the turn nearest the true yaw (a symmetric object is not charged for a relabelling). An episode keeps
the largest error of each stage (:meth:`PerceptionErrors.summary`: ``error_<stage>_mm``), which the evaluation's
scores record per episode and its report compares between the episodes that failed and those that succeeded.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kpflow.geometry.angles import yaw_of

from .keypoints import ObjectPose, pose_keypoints
from .specs import TaskSpec

#: the stages an episode's reads are sorted into (module docstring), in the order a task goes through them
STAGES = ("pick", "grasp", "held", "goal", "place")


def keypoint_error_mm(spec: TaskSpec, name: str, seen: ObjectPose, true: ObjectPose) -> float:
    """The largest distance (mm) between object ``name``'s keypoints at the ``seen`` pose and at the ``true`` one,
    both ordered by the turn nearest the true yaw."""
    reference = yaw_of(true.rot)
    seen_kp, true_kp = pose_keypoints(spec, name, seen, reference), pose_keypoints(spec, name, true, reference)
    return 1e3 * float(np.linalg.norm(seen_kp - true_kp, axis=-1).max())


def relative_error_mm(
    spec: TaskSpec, held: str, target: str, seen: dict[str, ObjectPose], true: dict[str, ObjectPose]
) -> float:
    """The largest distance (mm) between object ``held``'s keypoints relative to ``target``'s keypoint centre as
    ``seen`` and as ``true`` (poses by name): the placement's error, a bias shared by both objects cancelled."""

    def relative(poses: dict[str, ObjectPose]) -> np.ndarray:
        held_kp = pose_keypoints(spec, held, poses[held], yaw_of(true[held].rot))
        target_kp = pose_keypoints(spec, target, poses[target], yaw_of(true[target].rot))
        return held_kp - target_kp.mean(axis=0)

    return 1e3 * float(np.linalg.norm(relative(seen) - relative(true), axis=-1).max())


@dataclass
class PerceptionErrors:
    """The errors (mm) of one episode's reads, by stage (module docstring)."""

    largest: dict[str, float] = field(default_factory=dict)  #: each stage's largest error so far

    def add(self, stage: str, mm: float) -> None:
        if stage not in STAGES:
            raise ValueError(f"unknown stage {stage!r}; the stages are {', '.join(STAGES)}")
        self.largest[stage] = max(self.largest.get(stage, float(mm)), float(mm))

    def summary(self) -> dict[str, float]:
        """``error_<stage>_mm``: the largest error of each stage the episode went through."""
        return {f"error_{s}_mm": self.largest[s] for s in STAGES if s in self.largest}
