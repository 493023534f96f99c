"""The one policy builder: every policy of every task, built from configuration (``kpflow/conf/policy/*.yaml``, plain
functions Hydra instantiates) for ``evaluate`` and ``correct``; a policy in a checkpoint is built by
:class:`PolicyBuilder` (:func:`build`) as the checkpoint's config says (:mod:`.config`), for ``kpflow.load_policy``,
``evaluate`` and ``serve`` alike.

What is task-specific comes from the task's :class:`~.base.PolicyLayout`: the keypoints' dimension, their named
groups and roles (``objects``, ``goals``, ``robot``) and whether actions carry a rotation. Options that name
keypoints take group or role names: the source search's ``weights`` and ``frame`` (:class:`~.source_search.SourceSearch`,
one options object for every transporting policy, ``policy.search``) and ``fit_on`` (the keypoints a map is fitted on, or ``all``). Push-T's groups are ``block``,
``goal``, ``agent``; a robosuite task's are its object, its target and ``gripper``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Callable

from kpflow.core.policy import PolicyLayout
from kpflow.core.symmetry import ArmLimits

from ..data.chunks import ChunkDataModule
from ..data.source_index import SourceIndex
from ..maps import ILWRMap
from ..maps.base import TransportMap
from ..maps.learned import check_map_factory
from ..utils.releases import resolve_release
from .checks import INPUT_MARGIN
from .chunk_transport import TransportPolicy
from .nearest import NearestNeighbourPolicy
from .source_search import SourceSearch


def source_index_path(checkpoint: str | Path) -> Path:
    """Where a transporting policy's source index lives (:meth:`SourceIndex.save`): beside its checkpoint, named
    after it (``<name>.ckpt`` -> ``<name>.source_index.npz``)."""
    checkpoint = resolve_release(checkpoint)
    return checkpoint.with_name(f"{checkpoint.stem}.source_index.npz")


def _built(node):
    """A Hydra node instantiated (``_target_``), anything else as it is."""
    if isinstance(node, Mapping) and "_target_" in node:
        from hydra.utils import instantiate

        return instantiate(node)
    return node


def layout_of(task) -> PolicyLayout:
    """The :class:`PolicyLayout` a task declares (``task.policy_layout``; the task may be a config node)."""
    layout = getattr(_built(task), "policy_layout", None)
    if not isinstance(layout, PolicyLayout):
        raise ValueError(
            f"{type(task).__name__} declares no policy_layout: a learned or transporting policy needs the task's keypoint layout"
        )
    return layout


def check_checkpoint_fits(checkpoint: str, hparams: Mapping, task) -> None:
    """Raise ``ValueError`` naming ``checkpoint`` unless the keypoint layout of the K-CFM it holds (its
    hyper-parameters ``n_keypoints``, ``keypoint_dim``, ``action_dim``) is the one ``task`` declares: a checkpoint
    of another task is refused while the run is being built, before any episode."""
    task = _built(task)
    want = layout_of(task)
    have = (int(hparams["n_keypoints"]), int(hparams["keypoint_dim"]), int(hparams["action_dim"]))
    if have != want.shape:
        raise ValueError(
            f"{checkpoint} is a policy for {have[0]} keypoints in {have[1]}-D and {have[2]}-D actions, but {task.name} "
            f"shows {want.n_keypoints} keypoints in {want.keypoint_dim}-D and takes {want.action_dim}-D actions: pass a "
            f"checkpoint trained on {task.name}"
        )


def fit_on_indices(layout: PolicyLayout, fit_on: str | Sequence[str]) -> tuple[int, ...] | None:
    """The keypoint indices a map is fitted on: ``"all"`` (None: every keypoint) or group and role names."""
    if isinstance(fit_on, str):
        if fit_on == "all":
            return None
        fit_on = [fit_on]
    return layout.indices(*fit_on)


def within_reach(policy, layout: PolicyLayout, reach: float | None, turn_deg: float | None = None):
    """``policy`` shown its goal at most ``reach`` from its object and turned at most ``turn_deg`` degrees from it
    (:class:`~.subgoal.SubgoalPolicy`, planar tasks); as it is when both are None."""
    from .subgoal import SubgoalPolicy

    if reach is None and turn_deg is None:
        return policy
    if not layout.groups:
        raise ValueError("reach and turn_deg show the policy its goal nearer its object, but no keypoint layout names them: pass the task "
                         "(task=...) or release the checkpoint with task= (kpflow-release), which records its layout")  # fmt: skip
    if layout.keypoint_dim != 2 or not layout.indices("goals"):
        raise ValueError("reach and turn_deg show a planar task's goal nearer its object: this task has no planar goal")
    return SubgoalPolicy(policy, layout.indices("objects"), layout.indices("goals"), reach, turn_deg)


def _map_factory(make_map, layout: PolicyLayout, fit: tuple[int, ...] | None, what: str):
    make_map = _built(make_map)
    check_map_factory(make_map, len(fit) if fit else layout.n_keypoints, layout.keypoint_dim, what)
    return make_map


def make_kcfm(model, layout: PolicyLayout, steps: int | None = None, execute: int | None = None, input_margin: float | None = INPUT_MARGIN,
              reach: float | None = None, turn_deg: float | None = None, solver: str | None = None):  # fmt: skip
    """A loaded K-CFM as a policy (:class:`~.kcfm.policy.KCFMPolicy`), its goal within ``reach``/``turn_deg``; None:
    the checkpoint's own settings (:mod:`.settings`; ``reach``/``turn_deg`` False: the goal as observed)."""
    from .kcfm.policy import KCFMPolicy

    limits = model.settings.given(reach=reach, turn_deg=turn_deg)
    return within_reach(KCFMPolicy(model, steps, execute, input_margin, solver), layout, limits.reach, limits.turn_deg)


def make_transported_kcfm(model, index: SourceIndex, layout: PolicyLayout, make_map: Callable[[], TransportMap] = ILWRMap,
                          steps: int | None = None, execute: int | None = None, pull_back: str = "robot", fit_on: Sequence[int] | None = None,
                          input_margin: float | None = INPUT_MARGIN, reach: float | None = None, turn_deg: float | None = None,
                          solver: str | None = None, segments: bool = False, search: SourceSearch | Mapping | None = None,
                          arm: ArmLimits | None = None, alternatives: int = 3):  # fmt: skip
    """A loaded K-CFM transported online over ``index`` (:class:`~.transported_kcfm.TransportedKCFMPolicy`), phase
    by phase with ``segments`` (the layout's phases), its source chosen as ``search`` says
    (:class:`~.source_search.SourceSearch`: its choice; the index carries the weights and frame), each chunk checked
    against ``arm`` (the layout's symmetric correspondences chosen by its cost, up to ``alternatives`` sources
    tried); ``steps``, ``solver``, ``execute``, ``reach`` and ``turn_deg`` as in :func:`make_kcfm`."""
    from .transported_kcfm import TransportedKCFMPolicy

    choice = SourceSearch.of(search).choice()
    policy = TransportedKCFMPolicy(model, index, make_map, steps, execute, pull_back, fit_on, input_margin, layout, solver, segments, arm,
                                   alternatives, **choice)  # fmt: skip
    limits = model.settings.given(reach=reach, turn_deg=turn_deg)
    return within_reach(policy, layout, limits.reach, limits.turn_deg)


def resolved_search(layout: PolicyLayout, search: Mapping | None = None, fit_on: str | Sequence[str] | None = None):
    """``(SourceSearch, fit_on)`` of a transporting policy without phases: the options given, else the task's
    defaults (``layout.transport``), else the built-in ones (:meth:`~.config.TransportConfig.over`, the same
    layering as a transported K-CFM's)."""
    from .config import TransportConfig

    if isinstance(search, SourceSearch):
        search = search.record()
    given = TransportConfig.of({"segments": False, "fit_on": fit_on, "search": search}, "policy")
    resolved = given.over(defaults=layout.transport)
    return SourceSearch.of(resolved.search), resolved.fit_on


def nearest(demos: ChunkDataModule, task, horizon: int = 20, execute: int = 8, search: SourceSearch | Mapping | None = None,
            relative: bool = False):  # fmt: skip
    """Nearest neighbour over the demonstrations (:class:`~.nearest.NearestNeighbourPolicy`), compared with the
    weights and frame of ``search`` (:func:`resolved_search`; its choice unused: the nearest)."""
    layout = layout_of(task)
    search = resolved_search(layout, search)[0]
    policy = NearestNeighbourPolicy(search.index(_built(demos), layout, horizon), execute, relative)
    policy.resolved = {"search": search.record()}  # what a run's config.yaml records it used
    return policy


def transport(demos: ChunkDataModule, task, make_map: Callable[[], TransportMap] | None = None, horizon: int = 20,
              search: SourceSearch | Mapping | None = None, execute: int = 8, fit_on: str | Sequence[str] | None = None,
              max_step: float | None = None):  # fmt: skip
    """Policy transportation (:class:`~.chunk_transport.TransportPolicy`) over the demonstrations' index, its source
    found as ``search`` says (:class:`~.source_search.SourceSearch`), its map fitted on ``fit_on``, each executed
    step clipped to ``max_step``. ``make_map`` None: ILWR (``kpflow/conf/map/ilwr.yaml``); ``search`` and ``fit_on``
    not given: the task's defaults (``PolicyLayout.transport``), else the built-in ones (:func:`resolved_search`). A
    learned map is read now and checked against the keypoints it is fitted on."""
    layout = layout_of(task)
    search, fit_on = resolved_search(layout, search, fit_on)
    fit_on = fit_on if isinstance(fit_on, str) else list(fit_on)
    if make_map is None:
        from .config import map_factory

        make_map = map_factory("ilwr")
    fit = fit_on_indices(layout, fit_on)
    make_map = _map_factory(make_map, layout, fit, f"policy transportation (fit_on={fit_on})")
    policy = TransportPolicy(
        search.index(_built(demos), layout, horizon), make_map, execute, max_step, fit, layout, **search.choice()
    )
    policy.resolved = {"search": search.record(), "fit_on": fit_on}
    return policy


class PolicyBuilder:
    """A checkpoint read once, ready to build the policy its config says (:class:`~.config.PolicyConfig`), with
    ``overrides`` on top: the one way from a checkpoint to an acting policy (``kpflow.load_policy``,
    ``kpflow-evaluate``'s ``policy=kcfm | transported_kcfm`` and ``kpflow-serve`` all use it).

    ``overrides`` (None: none): ``kind`` (:data:`~.config.KINDS`), the settings (``steps``, ``solver``, ``execute``,
    ``reach``, ``turn_deg``; None keeps the checkpoint's, ``reach``/``turn_deg`` False: the goal as observed) and
    ``transport`` (options of :class:`~.config.TransportConfig`; None values: the checkpoint's, then the task's
    defaults, then the built-in ones). ``task``: the task the policy acts in (a task object or config node; None: the
    keypoint layout the checkpoint records, or for a checkpoint without one its bare shape, no named groups);
    ``demos``: a transporting policy's sources as a data node (None: the index saved beside the checkpoint,
    :func:`source_index_path`); ``input_margin``: how far outside its training keypoints an observation may lie
    (:mod:`.checks`).

    Everything is resolved and checked here, before any policy acts: a checkpoint of another task, a transport option
    the mode ignores or a kcfm given transport options (named), an unknown keypoint group, a map that does not fit
    the keypoints it is fitted on, ``arm`` on a task without arm limits. :attr:`config` is what was resolved;
    :meth:`build` returns a fresh policy (its own noise and decisions) sharing the loaded model and index."""

    def __init__(self, checkpoint: str | Path, overrides: Mapping | None = None, task=None, demos: ChunkDataModule | Mapping | None = None,
                 input_margin: float | None = INPUT_MARGIN) -> None:  # fmt: skip
        from ..utils.checkpoint import load_checkpoint
        from .config import KINDS, PolicyConfig, TransportConfig, map_factory
        from .kcfm.model import KCFM

        overrides = dict(overrides or {})
        if unknown := sorted(set(overrides) - {"kind", "transport", *SETTINGS}):
            raise ValueError(
                f"unknown policy option(s) {unknown}; the options are kind, transport and {', '.join(SETTINGS)}"
            )
        self.checkpoint = resolve_release(checkpoint)
        self.model = model = load_checkpoint(KCFM, self.checkpoint, map_location="cpu")
        stored: PolicyConfig = model.policy_config
        task = _built(task)
        if task is not None:
            check_checkpoint_fits(str(checkpoint), model.hparams, task)
            self.layout = layout_of(task)
        elif stored.layout is not None:
            self.layout = PolicyLayout.from_record(stored.layout, str(checkpoint))
        else:
            hp = model.hparams
            self.layout = PolicyLayout(int(hp.n_keypoints), int(hp.keypoint_dim), int(hp.action_dim))
        kind = overrides.get("kind") or stored.kind
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}; got {kind!r}")
        given = TransportConfig.of(overrides.get("transport"), "transport")
        settings = {k: overrides.get(k) for k in SETTINGS}
        self.steps, self.execute, self.solver = settings["steps"], settings["execute"], settings["solver"]
        self.reach, self.turn_deg, self.input_margin = settings["reach"], settings["turn_deg"], input_margin
        self.index = self.make_map = self.arm = None
        if kind == "kcfm":
            if given.record():
                raise ValueError(f"kind=kcfm is the K-CFM as it is, not transported: transport options {sorted(given.record())} are unused "
                                 "(kind=transported_kcfm transports it)")  # fmt: skip
            transport = None
        else:
            transport = given.over(stored.transport or TransportConfig(), defaults=self.layout.transport)
            self.fit_on = None if transport.segments else fit_on_indices(self.layout, transport.fit_on)
            self.make_map = _map_factory(map_factory(transport.map, transport.map_options), self.layout, self.fit_on,
                                         f"the transported K-CFM (fit_on={transport.fit_on})")  # fmt: skip
            if transport.arm:
                self.arm = getattr(task, "arm_limits", None)
                if self.arm is None:
                    raise ValueError(
                        f"transport.arm=true checks chunks against the task's arm_limits; {type(task).__name__} declares none"
                    )
            search = SourceSearch.of(transport.search)
            if demos is None:
                self.index = search.reindexed(SourceIndex.load(source_index_path(self.checkpoint)), self.layout)
            else:
                self.index = search.index(_built(demos), self.layout, int(model.hparams.horizon))
            self.search = search
        self.config = PolicyConfig(kind, model.settings.given(**settings), transport, self.layout.record())
        self._checked = self.build()  # checks the settings against the model now; the first build() hands it out

    def build(self):
        """A fresh policy as :attr:`config` says (its ``policy_config``: what a run records it used); the first is
        the one built to check the config, not built again."""
        policy, self._checked = getattr(self, "_checked", None), None
        if policy is not None:
            return policy
        policy = self._assembled()
        policy.policy_config = self.config
        return policy

    def _assembled(self):
        if self.config.kind == "kcfm":
            return make_kcfm(
                self.model,
                self.layout,
                self.steps,
                self.execute,
                self.input_margin,
                self.reach,
                self.turn_deg,
                self.solver,
            )
        t = self.config.transport
        return make_transported_kcfm(self.model, self.index, self.layout, self.make_map, self.steps, self.execute, t.pull_back, self.fit_on,
                                     self.input_margin, self.reach, self.turn_deg, self.solver, t.segments, self.search, self.arm,
                                     t.alternatives)  # fmt: skip


SETTINGS = ("steps", "solver", "execute", "reach", "turn_deg")


def build(checkpoint: str | Path, overrides: Mapping | None = None, task=None, demos: ChunkDataModule | Mapping | None = None,
          input_margin: float | None = INPUT_MARGIN):  # fmt: skip
    """The policy of ``checkpoint`` as its config says, ``overrides`` on top (:class:`PolicyBuilder`)."""
    return PolicyBuilder(checkpoint, overrides, task, demos, input_margin).build()


def kcfm(checkpoint: str, task, steps: int | None = None, execute: int | None = None, reach: float | None = None, turn_deg: float | None = None,
         input_margin: float | None = INPUT_MARGIN, solver: str | None = None):  # fmt: skip
    """``policy=kcfm``: the K-CFM at ``checkpoint`` for ``task``, as it is (:func:`build` with ``kind=kcfm``; the
    settings None: the checkpoint's)."""
    overrides = {
        "kind": "kcfm",
        "steps": steps,
        "execute": execute,
        "reach": reach,
        "turn_deg": turn_deg,
        "solver": solver,
    }
    return build(checkpoint, overrides, task, input_margin=input_margin)


SOURCES = ("auto", "saved", "data")


def transported_kcfm(checkpoint: str, demos: ChunkDataModule | Mapping | None, task, transport: Mapping | None = None, steps: int | None = None,
                     execute: int | None = None, reach: float | None = None, turn_deg: float | None = None,
                     input_margin: float | None = INPUT_MARGIN, solver: str | None = None, sources: str = "auto"):  # fmt: skip
    """``policy=transported_kcfm``: the K-CFM at ``checkpoint`` transported online (:func:`build` with
    ``kind=transported_kcfm``) over the index ``sources`` says: ``saved`` (beside the checkpoint,
    :func:`source_index_path`), ``data`` (over the episodes of ``demos``), ``auto`` (saved where there is one, else
    data); ``transport`` and the settings None: the checkpoint's, then the task's. The checkpoint is read and checked
    before the demonstrations are built (the config is not instantiated recursively: a refused file collects
    nothing)."""
    if sources not in SOURCES:
        raise ValueError(f"sources must be one of {SOURCES}; got {sources!r}")
    if sources == "auto":
        sources = "saved" if source_index_path(checkpoint).is_file() or demos is None else "data"
    if sources == "data" and demos is None:
        raise ValueError(
            "sources=data transports over the episodes of a data node: pass data=<node> (kpflow/conf/data/)"
        )
    demos = demos if sources == "data" else None
    overrides = {"kind": "transported_kcfm", "transport": transport, "steps": steps, "execute": execute, "reach": reach, "turn_deg": turn_deg,
                 "solver": solver}  # fmt: skip
    return build(checkpoint, overrides, task, demos, input_margin)
