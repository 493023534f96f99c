"""Hindsight goals: a demonstration relabelled with the goal it actually reached.

A demonstration that pushes an object towards a goal ends with the object at some pose, which is rarely the goal
exactly: the human Push-T demonstrations of Diffusion Policy stop at a coverage of 0.77-0.90, none of them at the
0.95 that counts as success. Read with its recorded goal, every late step of such a demonstration says "this push is
what to do when the object is a few px and degrees off the goal", although the push then leaves it there. Read with
the goal it reached, the same steps are a demonstration that ends exactly on its goal.

For an episode of ``T`` steps with object keypoints ``o_t [M, D]`` and goal keypoints ``g_t [M, D]`` (goal keypoint
``j`` is where object keypoint ``j`` belongs), relabelling sets every step's goal to the object's last keypoints,

    g_t <- o_{T-1}    for t = 0 .. T-1,

which is hindsight experience replay's "final" strategy (Andrychowicz et al. 2017, Sec. 4.5) applied to the
goal keypoints of the observation. Actions are unchanged: they are what was done, and it led exactly there.

A fragment of a longer episode is a choice: an expert takeover stored by interactive corrections
(:mod:`kpflow.tasks.pusht.corrections`, attrs ``source="correction"``) stops after a few dozen steps wherever the block then
is, and the rest of its episode, done by the policy, carried on towards the recorded goal. For learning it keeps
its recorded goal (:meth:`HindsightGoals.relabel`'s ``fragments``): relabelled, the takeovers that make up most of a corrected store say "stop
here", and K-CFM trained on a corrected store fails far more often (results/pusht_table1.md). A source
index relabels them (:meth:`~kpflow.data.source_index.SourceIndex.from_store`), which is where that reading measured
better; a learned policy reads them that way with ``data.relabel_fragments=true`` (the datamodule's key).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GOALS = ("recorded", "hindsight")  # how a demonstration's goal keypoints are read
FRAGMENT_SOURCES = ("correction",)  # episode attrs["source"] of parts of longer episodes (module docstring)


@dataclass(frozen=True)
class HindsightGoals:
    """Which observation keypoints are the object's and which the goal's, in corresponding order.

    Args:
        object: indices of the object's keypoints in an observation ``[K, D]``.
        goal: indices of the goal's keypoints, ``goal[j]`` the place of ``object[j]``.
    """

    object: tuple[int, ...]
    goal: tuple[int, ...]

    def __post_init__(self) -> None:
        if len(self.object) != len(self.goal) or not self.object:
            raise ValueError(
                f"object and goal need the same number (>= 1) of keypoints; got {len(self.object)} and {len(self.goal)}"
            )
        if set(self.object) & set(self.goal):
            raise ValueError(
                f"a keypoint cannot be both the object's and the goal's: {sorted(set(self.object) & set(self.goal))}"
            )

    def relabel(self, obs: np.ndarray, episode_ends: np.ndarray, fragments: np.ndarray | None = None) -> np.ndarray:
        """A copy of the concatenated observations ``obs [N, K, D]`` of episodes ending (exclusive) at the rows
        ``episode_ends`` (an :class:`~kpflow.data.episode_store.EpisodeStore`'s), each episode's goal keypoints set
        to its object's keypoints at its last row (module docstring), except the episodes marked True in
        ``fragments`` (bool, one per episode; None: none), which keep their goals as recorded."""
        obs = np.asarray(obs)
        used = (*self.object, *self.goal)
        if obs.ndim != 3 or min(used) < 0 or max(used) >= obs.shape[1]:
            raise ValueError(
                f"need observations [N, K, D] with keypoints {min(used)}..{max(used)}; got shape {obs.shape}"
            )
        ends = np.asarray(episode_ends, np.int64)
        if ends.ndim != 1 or len(ends) == 0 or ends[-1] != len(obs) or (np.diff(ends, prepend=0) < 1).any():
            raise ValueError(
                f"episode_ends must rise strictly from >= 1 to the number of rows ({len(obs)}); got {ends[:5]}..."
            )
        lengths = np.diff(ends, prepend=0)
        fragments = np.zeros(len(ends), bool) if fragments is None else np.asarray(fragments)
        if fragments.shape != ends.shape or fragments.dtype != bool:
            raise ValueError(
                f"fragments must be one bool per episode ({len(ends)}); got {fragments.dtype} {fragments.shape}"
            )
        rows = ~np.repeat(fragments, lengths)  # the rows to relabel
        last = np.repeat(ends - 1, lengths)[rows]  # each such row's episode's last row
        out = obs.copy()
        out[np.ix_(rows, list(self.goal))] = obs[last][:, list(self.object)]
        return out


def fragment_episodes(store) -> np.ndarray:
    """One bool per episode of an :class:`~kpflow.data.episode_store.EpisodeStore`: True where the episode is a
    fragment of a longer one (its attrs ``source`` in :data:`FRAGMENT_SOURCES`), whose goal stays as recorded."""
    return np.array([store.episode_attrs(i).get("source") in FRAGMENT_SOURCES for i in range(store.n_episodes)], bool)
