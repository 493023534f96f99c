"""A policy's configuration, saved in its checkpoint: loading it with no overrides builds the policy its results page
measured (LeRobot's pattern: one config record per policy kind).

* :class:`PolicyConfig`: the policy's ``kind`` (:data:`KINDS`: ``kcfm``, the K-CFM as it is; ``transported_kcfm``,
  the K-CFM transported online, Eq. 5), its :class:`~.settings.PolicySettings` (steps, solver, executed actions,
  the goal's reach and turn), for a transporting kind its :class:`TransportConfig`, and the keypoint layout of the
  task it was trained on (:meth:`~.base.PolicyLayout.record`).
* :class:`TransportConfig`: the map (``map``: a file of ``kpflow/conf/map/``, with ``map_options``, plain values
  set on it), whether the transport follows the task's phases (``segments``), the keypoints a map is fitted on
  without them (``fit_on``: group or role names, or ``all``), what is pulled back into the source scene
  (``pull_back``: ``robot`` or ``all``), how the source is found (``search``: the options of
  :class:`~.source_search.SourceSearch`), and whether chunks are checked against the arm (``arm``, with
  ``alternatives`` sources tried).

Which value a policy uses, first found wins (:meth:`TransportConfig.over`): the one given (a config key, an
argument), the checkpoint's record, the task's declared defaults (``PolicyLayout.transport``), the built-in
default (:data:`DEFAULTS`). An option the chosen mode ignores is refused by name when it is given or recorded:
``fit_on`` and the search's ``weights``/``frame`` with ``segments`` (each phase declares its own),
``alternatives`` without ``arm`` (:meth:`TransportConfig.check_used`); a task's defaults that the mode ignores are
dropped. ``pull_back: agent`` is read as ``robot`` (its old spelling).

In the checkpoint the record lives under :data:`CHECKPOINT_KEY` (``kind``, ``transport``, ``layout``; plain values
only, read with ``weights_only``), the settings under :data:`~.settings.CHECKPOINT_KEY` as before; a checkpoint
written before the record (no :data:`CHECKPOINT_KEY`) reads as a ``kcfm`` without a layout (:meth:`PolicyConfig.of_checkpoint`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

from .settings import CHECKPOINT_KEY as SETTINGS_KEY
from .settings import PolicySettings

#: The checkpoint's key of the record (beside ``state_dict``, ``hyper_parameters`` and ``policy_settings``).
CHECKPOINT_KEY = "policy_config"
KINDS = ("kcfm", "transported_kcfm")
PULL_BACK = ("robot", "all")
OLD_SPELLINGS = {"pull_back": {"agent": "robot"}}
#: What a transport uses where nothing else says (module docstring).
DEFAULTS = {
    "map": "ilwr",
    "map_options": {},
    "segments": False,
    "fit_on": "all",
    "pull_back": "robot",
    "search": {"weights": {"objects": 1.0, "goals": 1.0, "robot": 4.0}, "frame": "objects"},
    "arm": False,
    "alternatives": 3,
}
PLAIN = (str, int, float, bool, type(None))


def _plain(name: str, value: Any) -> Any:
    """``value`` as plain data (str, numbers, bools, None; lists and string-keyed mappings of them), else
    ``ValueError`` naming ``name``: what a checkpoint may hold and a config may give."""
    if isinstance(value, PLAIN):
        return value
    if isinstance(value, Mapping):
        return {str(k): _plain(f"{name}.{k}", v) for k, v in value.items()}
    if isinstance(value, Sequence):
        return [_plain(f"{name}[{i}]", v) for i, v in enumerate(value)]
    raise ValueError(f"{name} must hold plain values (strings, numbers, lists, mappings), got {type(value).__name__}")


@dataclass(frozen=True)
class TransportConfig:
    """How a transporting policy carries a chunk into the scene (module docstring); None: not set here."""

    map: str | None = None
    map_options: Mapping[str, Any] | None = None
    segments: bool | None = None
    fit_on: str | tuple[str, ...] | None = None
    pull_back: str | None = None
    search: Mapping[str, Any] | None = None
    arm: bool | None = None
    alternatives: int | None = None

    def __post_init__(self) -> None:
        for name in ("segments", "arm"):
            if getattr(self, name) is not None and not isinstance(getattr(self, name), bool):
                raise ValueError(f"transport.{name} must be true or false, got {getattr(self, name)!r}")
        if self.map is not None and (not isinstance(self.map, str) or not self.map.isidentifier()):
            raise ValueError(
                f"transport.map must name a file of kpflow/conf/map/ (ilwr, gp, affine, ...), got {self.map!r}"
            )
        if self.map_options is not None:
            options = _plain("transport.map_options", dict(self.map_options))
            if any(k.startswith("_") for k in options):
                raise ValueError(
                    f"transport.map_options sets the map's own options only; {sorted(k for k in options if k.startswith('_'))} are refused"
                )
            object.__setattr__(self, "map_options", options)
        if self.fit_on is not None:
            fit_on = self.fit_on if isinstance(self.fit_on, str) else tuple(str(n) for n in self.fit_on)
            if not fit_on:
                raise ValueError("transport.fit_on names no keypoints: give group or role names, or all")
            object.__setattr__(self, "fit_on", fit_on)
        if self.pull_back is not None:
            pull_back = OLD_SPELLINGS["pull_back"].get(self.pull_back, self.pull_back)
            if pull_back not in PULL_BACK:
                raise ValueError(f"transport.pull_back must be one of {PULL_BACK}; got {self.pull_back!r}")
            object.__setattr__(self, "pull_back", pull_back)
        if self.search is not None:
            from .source_search import SourceSearch

            search = _set_search(_plain("transport.search", dict(self.search)))
            SourceSearch.of(search)  # refuses an unknown option, naming the known ones
            object.__setattr__(self, "search", search)
        if self.alternatives is not None and (
            isinstance(self.alternatives, bool) or not isinstance(self.alternatives, int) or self.alternatives < 1
        ):
            raise ValueError(f"transport.alternatives must be an integer >= 1, got {self.alternatives!r}")

    @classmethod
    def of(cls, record: Any, where: str = "transport") -> TransportConfig:
        """The options of a mapping (a config node, a checkpoint's record; None: none set); ``ValueError`` naming
        ``where`` and the key for an unknown option or a bad value."""
        if record is None:
            return cls()
        if isinstance(record, TransportConfig):
            return record
        if not isinstance(record, Mapping):
            raise ValueError(f"{where} must be a mapping of transport options, got {type(record).__name__}")
        known = {f.name for f in fields(cls)}
        if unknown := sorted(set(map(str, record)) - known):
            raise ValueError(f"{where} has no option {', '.join(unknown)}; its options are {', '.join(sorted(known))}")
        try:
            return cls(**{str(k): v for k, v in record.items()})
        except (TypeError, ValueError) as e:
            raise ValueError(f"{where}: {e}") from None

    def record(self) -> dict:
        """The options that are set, as plain data (what a checkpoint stores)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items() if v is not None}

    def on(self, lower: TransportConfig) -> TransportConfig:
        """This config's options where set, else ``lower``'s; the search's option by option."""
        merged = {**lower.record(), **self.record()}
        search = merge_search(lower.search, self.search)
        return TransportConfig(**{k: v for k, v in merged.items() if k != "search"}, search=search or None)

    def over(self, *lower: TransportConfig, defaults: Mapping | None = None) -> TransportConfig:
        """Every option resolved: this config's where set, else the first of ``lower`` that sets it, else
        ``defaults`` (a task's, where the mode uses them), else :data:`DEFAULTS`; the search's options one by one
        the same way. Raises ``ValueError`` naming an option the resolved mode ignores that this config or
        ``lower`` sets (:meth:`check_used`)."""
        given = self
        for layer in lower:
            given = given.on(layer)
        task = TransportConfig.of(defaults or {}, "the task's transport defaults")
        segments, arm = (
            next(v for v in (getattr(given, n), getattr(task, n), DEFAULTS[n]) if v is not None)
            for n in ("segments", "arm")
        )
        given.check_used(segments, arm)
        resolved = {**DEFAULTS, **_used(task, segments, arm), **given.record(), "segments": segments, "arm": arm}
        resolved["search"] = merge_search(
            _used_search(DEFAULTS["search"], segments), _used_search(task.search or {}, segments), given.search
        )
        if segments:
            resolved["fit_on"] = "all"  # each phase's own (unused)
        return TransportConfig(**resolved)

    def check_used(self, segments: bool, arm: bool) -> None:
        """Raise ``ValueError`` naming an option set here that a transport with ``segments`` and ``arm`` ignores."""
        ignored = []
        if segments and self.fit_on is not None and self.fit_on != "all":
            ignored.append("fit_on")
        if segments:
            ignored += [f"search.{k}" for k in ("weights", "frame") if (self.search or {}).get(k) is not None]
        if not arm and self.alternatives is not None:
            ignored.append("alternatives")
        if ignored:
            why = (
                "segments=true fits each phase's map on, and searches relative to, what the task's phases declare"
                if segments
                else ""
            )
            why = "; ".join(
                w
                for w in (
                    why,
                    "alternatives are the sources tried when the arm cannot follow (arm=true)"
                    if not arm and "alternatives" in ignored
                    else "",
                )
                if w
            )
            raise ValueError(
                f"the transport ignores {', '.join(ignored)} ({why}): drop {'it' if len(ignored) == 1 else 'them'}"
            )


def _set_search(search: Mapping) -> dict:
    """The search options that are set: None entries (and None keypoint weights) dropped, ``weights`` left out when
    none is set."""
    out = {k: v for k, v in search.items() if v is not None}
    if isinstance(out.get("weights"), Mapping):
        out["weights"] = {k: w for k, w in out["weights"].items() if w is not None}
        if not out["weights"]:
            del out["weights"]
    return out


def merge_search(*layers: Mapping | None) -> dict:
    """Source search options layered lowest first (:class:`~.source_search.SourceSearch`'s keys): each layer's set
    options over the ones below, ``weights`` group by group (``{robot: 16}`` over ``{objects: 1, robot: 4}`` is
    ``{objects: 1, robot: 16}``; a later name wins where a group and a role name the same keypoints)."""
    out: dict = {}
    for layer in layers:
        layer = _set_search(layer or {})
        if "weights" in layer:
            layer["weights"] = {**dict(out.get("weights") or {}), **dict(layer["weights"])}
        out.update(layer)
    return out


def _used_search(search: Mapping, segments: bool | None) -> dict:
    return {k: v for k, v in search.items() if v is not None and not (segments and k in ("weights", "frame"))}


def _used(task: TransportConfig, segments: bool, arm: bool) -> dict:
    """A task's defaults without those the mode ignores (and without its search, resolved apart)."""
    out = {k: v for k, v in task.record().items() if k != "search"}
    if segments:
        out.pop("fit_on", None)
    if not arm:
        out.pop("alternatives", None)
    return out


@dataclass(frozen=True)
class PolicyConfig:
    """What a checkpoint's policy is and how it acts (module docstring)."""

    kind: str = "kcfm"
    settings: PolicySettings = field(default_factory=PolicySettings)
    transport: TransportConfig | None = None
    layout: Mapping[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"policy kind must be one of {KINDS}; got {self.kind!r}")

    @classmethod
    def of_checkpoint(cls, checkpoint: Mapping, where: str = "the checkpoint") -> PolicyConfig:
        """The config a checkpoint (its loaded dict) holds; one without :data:`CHECKPOINT_KEY` is a ``kcfm`` with
        the settings it records. ``ValueError`` naming ``where`` and the key for a malformed record."""
        settings = PolicySettings.from_record(checkpoint.get(SETTINGS_KEY), where)
        record = checkpoint.get(CHECKPOINT_KEY)
        if record is None:
            return cls(settings=settings)
        if not isinstance(record, Mapping):
            raise ValueError(f"{where}: {CHECKPOINT_KEY!r} must be a mapping, got {type(record).__name__}")
        if unknown := sorted(set(map(str, record)) - {"kind", "transport", "layout"}):
            raise ValueError(
                f"{where}: {CHECKPOINT_KEY!r} has unknown key(s) {unknown}; known: kind, transport, layout"
            )
        layout = record.get("layout")
        if layout is not None:
            from kpflow.core.policy import PolicyLayout

            PolicyLayout.from_record(layout, where)  # a malformed layout is refused now, naming the file
        try:
            return cls(
                str(record.get("kind", "kcfm")),
                settings,
                TransportConfig.of(record.get("transport"), f"{where}: transport"),
                layout,
            )
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None

    def record(self) -> dict:
        """The record a checkpoint stores under :data:`CHECKPOINT_KEY` (the settings apart, under their own key)."""
        out: dict = {"kind": self.kind}
        if self.transport is not None and self.transport.record():
            out["transport"] = self.transport.record()
        if self.layout is not None:
            out["layout"] = dict(self.layout)
        return out

    def given(
        self, kind: str | None = None, transport: TransportConfig | Mapping | None = None, **settings
    ) -> PolicyConfig:
        """This config with ``kind``, transport options and settings given on top (None keeps this one's)."""
        merged = TransportConfig.of(transport).on(self.transport or TransportConfig())
        return replace(self, kind=kind or self.kind, settings=self.settings.given(**settings), transport=merged)


def map_factory(name: str, options: Mapping | None = None):
    """A factory of unfitted maps from a file of ``kpflow/conf/map/`` (``name``: ``ilwr``, ``gp``, ``affine``, ...)
    with plain ``options`` set on it: what a checkpoint's ``transport.map`` names. The classes built are the
    package's own files' (a checkpoint names a file, never a class: nothing it holds is imported or called)."""
    from importlib.resources import files

    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    folder = files("kpflow.conf") / "map"
    known = sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))
    if name not in known:
        raise ValueError(f"transport.map={name!r} names no map of kpflow/conf/map/; the maps are {', '.join(known)}")

    def node(n: str):
        cfg = OmegaConf.load(str(folder / f"{n}.yaml"))
        bases = [node(b) for b in cfg.pop("defaults", []) if b != "_self_"]
        return OmegaConf.merge(*bases, cfg)

    cfg = OmegaConf.merge(node(name), OmegaConf.create(dict(options or {})))
    try:
        return instantiate(cfg)
    except Exception as e:  # a missing required option (learned: its checkpoint), a wrong type
        raise ValueError(
            f"transport.map={name!r} with options {dict(options or {})} does not build a map: {e}"
        ) from None
