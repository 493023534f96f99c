"""Online transport of a K-CFM policy (the paper's Eq. 5): ``a = phi(f(phi^-1(x)))``.

At every decision, with ``T`` the observed keypoints and ``x`` the robot's state (its keypoints: the task's
:class:`~.base.PolicyLayout` role ``robot``; Push-T's agent):

1. ``S``: a configuration the K-CFM was trained on (a :class:`SourceIndex` over its training data), the nearest or
   drawn among the nearest, with stuck detection (:class:`~.source_choice.SourceChoice`);
2. ``phi``: a keypoint map fitted so that ``phi(S) ~= T`` (ILWR by default), on the keypoints ``fit_on`` (all by
   default; Push-T: the block and the agent, see :mod:`.chunk_transport`);
3. ``phi^-1(x)``: the robot pulled back into the source scene. The K-CFM's input is ``S`` with its robot replaced
   by ``phi^-1(x)`` (``pull_back="robot"``; ``"agent"``, its old spelling, is read the same): a scene it was trained on, exactly, with the robot where the map puts
   it. ``pull_back="all"`` pulls every observed keypoint back instead. A K-CFM with an observation history
   (``n_obs > 1``) sees each earlier frame ``T_j`` as the current input moved by ``phi^-1(T_j) - phi^-1(T)``, the
   motion since then pulled back (for ``pull_back="all"`` that is ``phi^-1(T_j)`` itself);
4. ``f``: the K-CFM samples a chunk of absolute targets there;
5. ``phi``: the chunk is pushed forward into the observed scene: positions by ``phi``, a 6-D rotation (the
   robosuite tasks' end-effector targets) by the polar factor of phi's Jacobian, the gripper as it is
   (:func:`~.chunk_transport.transport_chunk`).

This addresses the failure modes of its two ingredients:

* policy transportation (:class:`~kpflow.policies.chunk_transport.TransportPolicy`) replays the chunk of one
  nearest source and relies on the map alone to adapt it, so the map has to deform that single demonstration hard
  whenever the scene (the agent's position above all) differs from the source, and the chunk's shape is only ever
  that of the one demonstration;
* the K-CFM generalises from all its training data but is only reliable near it: on unseen inputs (a block
  elsewhere in the workspace, a rotated scene) its chunks become noisy and wrong.

Why only the agent is pulled back: a map fitted to 25 keypoints is not exact everywhere, so pulling the whole
observation back leaves the keypoints a few px off their source and the T shapes the K-CFM sees are no longer rigid
T shapes. The K-CFM reacts strongly to that: ``benchmarks/transported_chunks.py`` measures each choice's chunks
against demonstrated ones held out of the index (``results/pusht_table1.md``, "What the numbers say"), and pulling
every keypoint back errs about twice as much as the robot alone. (With a rigid map the two choices agree, and a goal-frame
K-CFM is equivariant to rigid motions: transport then changes nothing at all.)

Segment-aware transport (``phases``, :mod:`.phases`): where the task declares phases and the policy is asked to
follow them, steps 1-3 follow the phase of the observation, read from its keypoints (the jaws holding the object
or not): the source is searched among the training configurations of the same phase, relative to that phase's
``frame`` with its ``weights``; ``phi`` is fitted on the phase's ``fit_on`` keypoints (before a grasp the object to
pick, after it the target); the robot and the phase's ``carried`` keypoints (the held object) are pulled back.
Each phase is then carried in the frame of the object that matters in it, as a demonstration generator carries
each segment, and the map never has to stretch the space between two objects that moved independently.

Symmetric correspondences and the arm's limits (``arm``, an :class:`~.symmetry.ArmLimits`; the layout's
``symmetries``, :mod:`.symmetry`): where a task's keypoints can be relabelled without changing the task (a square
peg's quarter turns, the jaws' half turn), each relabelling ``c`` the phase admits gives its own map ``phi_c`` and
its own transported chunk, and the arm's cost rates them. At a phase's first decision the cheapest the arm can
follow is taken; it is kept while the arm can follow its chunks, and when one cannot be followed (a joint past its
range, a target out of reach) the other correspondences are tried, cheapest first, then the ``alternatives - 1``
next nearest sources. Every chunk sent has passed the check, unless none of them did: then the first is sent
and the decision counted in ``unfollowable`` (the arm's controller stops at its limits). Without ``arm`` the
identity is the only correspondence and nothing is checked: the policy is as it was.

The observation is held to the K-CFM's training range before anything is fitted, and the K-CFM's input after the
pull-back too (:meth:`~kpflow.policies.kcfm.KCFM.check_in_range`); actions that come out NaN or inf are refused
(:func:`~kpflow.policies.checks.check_actions`), as :class:`~kpflow.policies.kcfm.policy.KCFMPolicy` does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch

from kpflow.core.phases import Phase, Phases
from kpflow.core.policy import PolicyLayout
from kpflow.core.symmetry import ArmLimits, Symmetry, phase_correspondences

from ..data.source_index import SourceIndex
from ..geometry.angles import yaw_rotation
from ..geometry.rotations import matrix_to_rot6d, rot6d_to_matrix
from ..maps import ILWRMap
from ..maps.base import TransportMap
from .checks import INPUT_MARGIN, check_actions
from .chunk_transport import fitted_keypoints, robot_and_rotation, transport_chunk
from .kcfm.model import KCFM
from .kcfm.policy import KCFMPolicy
from .source_choice import SourceChoice

PULL_BACK = ("robot", "all")
OLD_PULL_BACK = {"agent": "robot"}  # the old spelling, still read


@dataclass(frozen=True)
class PhaseTransport:
    """What a decision in one phase uses: the ``phase`` (None: one phase for the whole task), the source ``choice``
    over its training configurations (``members``: their rows in the full index), the keypoints the map is
    ``fit_on``, those ``pulled`` back (the robot and what it carries) and the ``correspondences`` it may choose
    among (:func:`~.symmetry.phase_correspondences`; the identity alone without them)."""

    phase: Phase | None
    choice: SourceChoice
    members: np.ndarray
    fit_on: slice | np.ndarray
    pulled: np.ndarray
    correspondences: tuple[Symmetry, ...]


def source_phases(index: SourceIndex, phases: Phases) -> np.ndarray:
    """The phase of each of the index's configurations ``[N]`` (an index into ``phases.phases``): read by the same
    rule as an observation's, and where the index knows its episodes, every configuration after an episode's first
    hold in the held phase, the segment it belongs to (the release and the retreat after it end the place: they are
    no configurations to pick from)."""
    which = phases.index(index.keypoints)
    if index.episodes is None:
        return which
    held = next((i for i, p in enumerate(phases.phases) if p.holding), None)
    if held is None:
        return which
    holding = which == held
    for episode in np.unique(index.episodes):
        rows = np.flatnonzero(index.episodes == episode)
        if holding[rows].any():
            which[rows[int(np.argmax(holding[rows])) :]] = held
    return which


def phase_transports(
    index: SourceIndex, layout: PolicyLayout, phases: Phases, choice: dict, symmetries: Sequence[Symmetry] = ()
) -> list[PhaseTransport]:
    """One :class:`PhaseTransport` per phase of ``phases``: the index's configurations of that phase
    (:func:`source_phases`) searched relative to its ``frame`` with its ``weights``, with the correspondences
    ``symmetries`` admit in it (:func:`~.symmetry.phase_correspondences`; none: the identity alone)."""
    which = source_phases(index, phases)
    out = []
    for i, phase in enumerate(phases.phases):
        members = np.flatnonzero(which == i)
        if not len(members):
            raise ValueError(
                f"no training configuration of the source index is in phase {phase.name!r}: it cannot be transported segment by segment"
            )
        sub = SourceIndex(
            index.keypoints[members], index.chunks[members], layout.weights(phase.weights), layout.indices(*phase.frame)
        )
        pulled = np.asarray(
            sorted({*layout.indices("robot"), *(layout.indices(*phase.carried) if phase.carried else ())})
        )
        fit_on = np.asarray(layout.indices(*phase.fit_on))
        correspondences = tuple(phase_correspondences(symmetries, layout.n_keypoints, fit_on, phase.holding))
        out.append(PhaseTransport(phase, SourceChoice(sub, **choice), members, fit_on, pulled, correspondences))
    return out


class TransportedKCFMPolicy:
    """K-CFM transported online by a keypoint map: ``act(obs) = phi(f(phi^-1(T)))`` (module docstring, Eq. 5).

    Args:
        model: a trained K-CFM.
        index: its training configurations (e.g. ``SourceIndex.from_store(store, episodes=train_episodes,
            reference=PUSHT_BLOCK)``); only their keypoints are used.
        make_map: builds an unfitted map with an inverse (``ILWRMap``: exact inverse, rigid alignment first).
        steps, solver: network calls per chunk and the sampler (:class:`~kpflow.policies.kcfm.policy.KCFMPolicy`;
            None: the model's own).
        execute: how many actions of the chunk :meth:`act` returns (None: the checkpoint's setting, else 8).
        pull_back: ``"robot"`` (the source scene with the robot pulled back) or ``"all"`` (every observed keypoint
            pulled back); see the module docstring.
        fit_on: indices of the keypoints the map is fitted on (None: all).
        input_margin: how far outside the K-CFM's training keypoints an observation may lie
            (:class:`~kpflow.policies.kcfm.policy.KCFMPolicy`); None: no range check.
        layout: the task's :class:`~.base.PolicyLayout` (the robot's keypoints, whether actions carry a rotation);
            required (None is refused, naming it).
        segments: follow the layout's phases (module docstring; ``fit_on`` and the index's weights and frame are then
            each phase's own); the layout must declare them.
        arm: the task's :class:`~.symmetry.ArmLimits`: each chunk is checked against the arm and the layout's
            symmetric correspondences are chosen by its cost (module docstring); None: no check, the identity.
        alternatives: with ``arm``, how many sources (the choice's, then the nearest others) a decision may try.
        choice: :class:`~.source_choice.SourceChoice`'s options (``candidates``, ``stuck_decisions``, ...).

    After :meth:`act`, ``last_source`` (index of ``S`` in ``index``), ``last_map`` (``phi``), ``last_phase`` (the
    phase's name, None without phases), ``last_pullback`` (the K-CFM's input) and ``last_correspondence`` (the
    :class:`~.symmetry.Symmetry` taken) describe the decision; ``unfollowable`` counts the episode's decisions whose
    every candidate failed the arm's check.
    """

    def __init__(
        self,
        model: KCFM,
        index: SourceIndex,
        make_map: Callable[[], TransportMap] = ILWRMap,
        steps: int | None = None,
        execute: int | None = None,
        pull_back: str = "robot",
        fit_on: Sequence[int] | None = None,
        input_margin: float | None = INPUT_MARGIN,
        layout: PolicyLayout | None = None,
        solver: str | None = None,
        segments: bool = False,
        arm: ArmLimits | None = None,
        alternatives: int = 3,
        **choice,
    ) -> None:
        if arm is not None and not isinstance(arm, ArmLimits):
            raise ValueError(
                f"arm must have cost(obs, chunk) (kpflow.core.symmetry.ArmLimits), got {type(arm).__name__}"
            )
        if not (isinstance(alternatives, int) and alternatives >= 1):
            raise ValueError(f"alternatives must be an integer >= 1, got {alternatives!r}")
        self.arm, self.alternatives = arm, alternatives
        self.policy = KCFMPolicy(
            model, steps, execute, input_margin, solver
        )  # validates steps, solver, execute and input_margin
        self.n_obs = self.policy.n_obs
        k, d = int(model.hparams.n_keypoints), int(model.hparams.keypoint_dim)
        if index.keypoints.shape[1:] != (k, d):
            raise ValueError(f"the index holds keypoints {index.keypoints.shape[1:]}; the model takes ({k}, {d})")
        robot, self.rotation = robot_and_rotation(layout, k)
        pull_back = OLD_PULL_BACK.get(pull_back, pull_back)
        if pull_back not in PULL_BACK:
            raise ValueError(f"pull_back must be one of {PULL_BACK}; got {pull_back!r}")
        self.index, self.make_map, self.pull_back = index, make_map, pull_back
        symmetries = layout.symmetries if arm is not None else ()  # without the arm's cost, nothing to choose by
        self.phases = None
        if segments:
            if layout is None or layout.phases is None:
                raise ValueError(
                    "segments=true follows the phases a task declares (PolicyLayout.phases); this task declares none"
                )
            self.phases = layout.phases
            self.transports = phase_transports(index, layout, layout.phases, choice, symmetries)
        else:
            fit = fitted_keypoints(fit_on, k)
            correspondences = tuple(phase_correspondences(symmetries, k, np.arange(k)[fit], None))
            self.transports = [
                PhaseTransport(None, SourceChoice(index, **choice), np.arange(len(index)), fit, robot, correspondences)
            ]
        self.last_transport = self.transports[0]
        self.last_source: int | None = None
        self.last_phase: str | None = None
        self.last_map: TransportMap | None = None
        self.last_pullback: np.ndarray | None = None
        self.last_correspondence: Symmetry | None = None
        self.kept: dict[int, int] = {}  # phase (its transport's position) -> the correspondence kept in it
        self.unfollowable = 0

    @property
    def model(self) -> KCFM:
        return self.policy.model

    @property
    def steps(self) -> int:
        return self.policy.steps

    @property
    def execute(self) -> int:
        return self.policy.execute

    @property
    def source(self) -> SourceChoice:
        """The source choice of the last decision's phase (the first phase's before any; the only one without phases)."""
        return self.last_transport.choice

    def reset(self, seed: int | None = None) -> None:
        """Reseed the K-CFM's sampling noise and the source draw with ``seed`` (0 when None) and forget the last decision."""
        self.policy.reset(seed)
        for transport in self.transports:
            transport.choice.reset(seed)
        self.last_source, self.last_phase, self.last_map, self.last_pullback = None, None, None, None
        self.last_transport, self.last_correspondence = self.transports[0], None
        self.kept, self.unfollowable = {}, 0

    def act(self, obs: dict) -> np.ndarray:
        """The first ``execute`` actions ``[execute, A]`` (float64) of ``phi(f(phi^-1(x)))`` for ``T = obs["keypoints"]``
        (and ``obs["keypoints_history"] [n_obs, K, D]`` for a K-CFM with an observation history).

        Raises:
            ValueError: an observation of the wrong shape, not finite or far outside the K-CFM's training data;
                actions that came out NaN or inf.
        """
        if self.n_obs == 1:
            self.model.check_in_range(obs["keypoints"], self.policy.input_margin)  # shape, finite, within range
            frames = [np.asarray(obs["keypoints"], dtype=np.float64)]
        elif "keypoints_history" not in obs:
            raise ValueError(
                f"this K-CFM conditions on the last {self.n_obs} observations: pass obs['keypoints_history'] [{self.n_obs}, K, D]"
            )
        else:
            self.model.check_in_range(obs["keypoints_history"], self.policy.input_margin)
            frames = list(np.asarray(obs["keypoints_history"], dtype=np.float64))
        target = frames[-1]
        which = 0 if self.phases is None else int(self.phases.index(target[None])[0])
        transport = self.transports[which]
        first = int(transport.members[transport.choice.choose(target)])
        if self.arm is None:
            source, c, chosen = first, 0, self._transported(transport, first, transport.correspondences[0], frames)
        else:
            source, c, chosen = self._followable(obs, transport, which, first, target, frames)
        out, phi, pullback = chosen
        self.last_source, self.last_map, self.last_pullback = source, phi, pullback
        self.last_transport, self.last_phase = transport, transport.phase.name if transport.phase else None
        self.last_correspondence = transport.correspondences[c]
        return check_actions(out, "the transported K-CFM")

    def _transported(self, transport: PhaseTransport, i: int, correspondence: Symmetry, frames: list[np.ndarray]):
        """The chunk ``[execute, A]`` of source ``i`` under ``correspondence``, with its map and the K-CFM's input."""
        perm = np.asarray(correspondence.perm)
        seen = np.stack(frames)[:, perm]  # the observation relabelled: T_c = T[perm]
        target_t = torch.from_numpy(seen[-1])
        source_t = torch.from_numpy(self.index.keypoints[i].astype(np.float64))
        phi = self.make_map().fit(source_t[transport.fit_on], target_t[transport.fit_on])
        with torch.no_grad():  # one inverse for every frame: the last one is the current observation
            back = phi.inverse(torch.from_numpy(seen)).to(torch.float64)  # [n_obs, K, D]
            if self.pull_back == "all":
                pullback = back[-1]
            else:
                pullback = source_t.clone()
                pullback[transport.pulled] = back[-1][transport.pulled]
            if self.n_obs > 1:
                pullback = pullback + (back - back[-1])
        chunk = self.policy.act({"keypoints" if self.n_obs == 1 else "keypoints_history": pullback.numpy()})
        dim = seen.shape[-1]
        out = transport_chunk(phi, chunk, dim, self.rotation)
        if correspondence.tool_turn and self.rotation:  # the tool turned about its own z axis: R -> R Rz(turn)
            out[:, dim : dim + 6] = matrix_to_rot6d(
                rot6d_to_matrix(out[:, dim : dim + 6]) @ yaw_rotation(correspondence.tool_turn)
            )
        return out, phi, pullback.numpy()

    def _followable(
        self, obs: dict, transport: PhaseTransport, which: int, first: int, target: np.ndarray, frames: list[np.ndarray]
    ):
        """``(source, correspondence, (chunk, map, input))`` of the first candidate the arm can follow (module
        docstring): the phase's kept correspondence of the chosen source, else the cheapest of the others, else the
        next sources'; the first candidate when none can be followed."""
        near, _ = transport.choice.index.query_k(target, min(self.alternatives, len(transport.members)))
        sources = [first] + [int(transport.members[j]) for j in near if int(transport.members[j]) != first][
            : self.alternatives - 1
        ]
        n, kept = len(transport.correspondences), self.kept.get(which)
        fallback = None
        for source in sources:
            order = ([kept] + [c for c in range(n) if c != kept]) if kept is not None else list(range(n))
            rated = []
            for c in order:
                candidate = self._transported(transport, source, transport.correspondences[c], frames)
                fallback = fallback or (source, c, candidate)
                cost = float(self.arm.cost(obs, candidate[0]))
                if c == kept and np.isfinite(cost):
                    return source, c, candidate  # the kept correspondence while the arm follows it
                rated.append((cost, c, candidate))
            cost, c, candidate = min(rated, key=lambda r: r[0])  # the first of the cheapest
            if np.isfinite(cost):
                self.kept[which] = c
                return source, c, candidate
        self.unfollowable += 1
        return fallback
