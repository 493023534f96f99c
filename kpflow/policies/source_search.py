"""How a transporting policy finds its source: one options object for nearest neighbour, policy transportation and the
transported K-CFM (``policy.search={candidates: 5}`` on the command line, ``policy.transport.search`` for a transported
K-CFM, ``transport.search`` for ``kpflow-serve``). An option not given is the task's (``PolicyLayout.transport``:
Push-T detects a stuck block), else :data:`~.config.DEFAULTS`'s (:meth:`~.config.TransportConfig.over`); keypoint
weights are layered group by group.

A source is a demonstrated configuration ``S`` of the :class:`~kpflow.data.source_index.SourceIndex` near the
observed one. The index compares configurations by a weighted distance over keypoint groups (``weights``: group or
role -> weight, e.g. ``{objects: 1, goals: 1, robot: 4}``) relative to ``frame`` (a group or role whose keypoints the
configurations are aligned on, or ``world``: as they are). The source is then chosen among the nearest
(:class:`~.source_choice.SourceChoice`): the nearest with ``candidates = 1``, else drawn among the ``candidates``
nearest with rank weights ``exp(-rank / temperature)``; after ``stuck_decisions`` decisions over which the object
moved less than ``stuck_distance``, drawn uniformly among ``stuck_candidates`` nearest (``stuck_decisions: false``:
never, whatever the task's default; ``null`` means not given here).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields

from kpflow.core.policy import PolicyLayout

from ..data.chunks import ChunkDataModule
from ..data.episode_store import EpisodeStore
from ..data.source_index import SourceIndex


@dataclass(frozen=True)
class SourceSearch:
    """The source search's options (module docstring); their checks are :class:`~.source_choice.SourceChoice`'s and
    the layout's (a weight or frame naming no group or role is refused, naming the ones there are)."""

    weights: Mapping[str, float] | None = None
    frame: str = "world"
    candidates: int = 1
    temperature: float = 1.2
    stuck_decisions: int | None = None
    stuck_distance: float = 2.0
    stuck_candidates: int = 50

    def __post_init__(self) -> None:
        if self.stuck_decisions is False:  # "never", said where a null would mean "the task's default"
            object.__setattr__(self, "stuck_decisions", None)
        elif self.stuck_decisions is True:
            raise ValueError("stuck_decisions must be a number of decisions >= 1, or false (never); got true")

    @classmethod
    def of(cls, search: SourceSearch | Mapping | None) -> SourceSearch:
        """``search`` as options: None for the defaults, a mapping (a config node) of some of the fields (an unknown
        key is refused, naming the known ones)."""
        if search is None:
            return cls()
        if isinstance(search, SourceSearch):
            return search
        if not isinstance(search, Mapping):
            raise ValueError(
                f"the source search must be a mapping of {[f.name for f in fields(cls)]}, got {type(search).__name__}"
            )
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(search) - known)
        if unknown:
            raise ValueError(
                f"the source search has no option {', '.join(unknown)}; its options are {', '.join(sorted(known))}"
            )
        values = dict(search)
        if values.get("weights") is not None:
            values["weights"] = {str(k): float(v) for k, v in dict(values["weights"]).items()}
        return cls(**values)

    def record(self) -> dict:
        """Every option as plain data (what a run's config records)."""
        out = asdict(self)
        out["weights"] = None if self.weights is None else dict(self.weights)
        return out

    def choice(self) -> dict:
        """The options of :class:`~.source_choice.SourceChoice`."""
        return {k: v for k, v in asdict(self).items() if k not in ("weights", "frame")}

    def frame_indices(self, layout: PolicyLayout) -> tuple[int, ...] | None:
        """The keypoints configurations are compared relative to (``world``: None)."""
        return None if self.frame == "world" else layout.indices(self.frame)

    def index(self, demos: ChunkDataModule, layout: PolicyLayout, horizon: int) -> SourceIndex:
        """A :class:`SourceIndex` over every step of the episodes the data node ``demos`` trains on (its store, its
        first ``max_episodes``; goals read as the node says: ``data.goals``), chunks of ``horizon`` actions."""
        if not isinstance(demos, ChunkDataModule):
            raise ValueError(
                f"demos must be a data node of demonstrations (a ChunkDataModule, kpflow/conf/data/), got {type(demos).__name__}"
            )
        store = EpisodeStore(demos.path)
        n = store.n_episodes if demos.max_episodes is None else min(store.n_episodes, int(demos.max_episodes))
        return SourceIndex.from_store(store, horizon, layout.weights(self.weights), self.frame_indices(layout), range(n), demos.obs_key,
                                      demos.action_key, demos.hindsight)  # fmt: skip

    def reindexed(self, saved: SourceIndex, layout: PolicyLayout) -> SourceIndex:
        """A saved index (:meth:`SourceIndex.load`) searched with these weights and this frame."""
        return SourceIndex(
            saved.keypoints, saved.chunks, layout.weights(self.weights), self.frame_indices(layout), saved.episodes
        )
