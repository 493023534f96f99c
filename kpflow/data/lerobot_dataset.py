"""Episode stores as LeRobot datasets (format v3.0, what ``lerobot.datasets.LeRobotDataset(repo_id, root=...)``
reads), and back.

::

    meta/info.json                                  codebase_version "v3.0", fps, totals, splits, path templates,
                                                    features {name: {dtype, shape, names}} (the five default ones last)
    meta/stats.json                                 per feature: min, max, mean, std, count, q01, q10, q50, q90, q99
    meta/tasks.parquet                              task_index, with the task string as the (pandas) index
    meta/episodes/chunk-000/file-000.parquet        per episode: episode_index, tasks, length, data/chunk_index,
                                                    data/file_index, dataset_from_index, dataset_to_index,
                                                    meta/episodes/{chunk,file}_index, stats/<feature>/<stat>
    data/chunk-XXX/file-XXX.parquet                 one row per frame: each feature a fixed-size float32 list, then
                                                    timestamp, frame_index, episode_index, index, task_index

Several episodes share a data file until it reaches ``data_files_size_in_mb``; a chunk holds ``chunks_size`` files
(lerobot's ``update_chunk_file_indices``). A store field of any shape becomes a flat float32 vector feature: the
``keypoints [T, K, D]`` as ``observation.state`` named ``k0.x, k0.y, ...`` (so :func:`import_lerobot` restores
their shape), the ``action`` as ``action``, any other field ``f`` as ``observation.f``. Videos are not written.
The dataset is built in a temporary folder and renamed into place: a reader never sees half of one.

Another dataset's ``observation.state`` is read as keypoints through a :class:`KeypointMap` (``data.keypoint_map`` in
a data config): which of its named columns are each keypoint's x, y[, z], and which are the robot's, placed last.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from kpflow.utils.formats import check_parquet_rows, read_parquet
from kpflow.utils.io import atomic_dir

from .episode_store import EpisodeStore

CODEBASE_VERSION = "v3.0"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DEFAULT_FEATURES = {name: {"dtype": dtype, "shape": [1], "names": None} for name, dtype in
                    (("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"), ("index", "int64"), ("task_index", "int64"))}  # fmt: skip
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
AXES = "xyz"
MAX_WIDTH = 1 << 16  # values per frame of an imported feature (states and actions; images live in videos)


def feature_name(field: str) -> str:
    return {"keypoints": "observation.state", "action": "action"}.get(field, f"observation.{field}")


def _width(spec: dict, where: str) -> int:
    """Values per frame of a feature (the product of its ``shape``), at most :data:`MAX_WIDTH`."""
    shape = spec.get("shape") if isinstance(spec, dict) else None
    if not isinstance(shape, list) or not all(isinstance(n, int) and n >= 1 for n in shape):
        raise ValueError(f"{where} has no valid shape in info.json ({shape!r})")
    width = int(np.prod(shape))
    if width > MAX_WIDTH:
        raise ValueError(
            f"{where} has {width} values per frame; kpflow imports state and action features of at most {MAX_WIDTH}"
        )
    return width


def flat_names(names) -> list | None:
    """A feature's value names as one flat list, in LeRobot's spellings: a list, a list of lists (one per axis of a
    multi-dimensional feature), ``{"motors": [...]}``-style (one list under one key), or one comma-separated string."""
    if isinstance(names, str):
        return [n.strip() for n in names.split(",")]
    if isinstance(names, dict) and len(names) == 1:
        names = next(iter(names.values()))
    if isinstance(names, list) and names and all(isinstance(n, list) for n in names):
        return [n for row in names for n in row]
    return names if isinstance(names, list) else None


def keypoint_layout(names: list[str] | None) -> tuple[int, int] | None:
    """``(K, D)`` when ``names`` are exactly kpflow's keypoint names ``k0.x, k0.y, ..., k<K-1>.<axis D-1>`` in that
    order (what :func:`export_lerobot` writes; in any of :func:`flat_names`' spellings), else None: repeated,
    missing or shuffled names are not keypoints."""
    names = flat_names(names)
    if not names or not all(isinstance(n, str) and re.fullmatch(r"k\d+\.[xyz]", n) for n in names):
        return None
    d = len({n.split(".")[1] for n in names})
    if len(names) % d:
        return None
    k = len(names) // d
    return (k, d) if list(names) == [f"k{i}.{AXES[j]}" for i in range(k) for j in range(d)] else None


MAP_HELP = "docs/concepts/data.md#lerobot-datasets-with-other-state-names"
MAP_EXAMPLE = "data.keypoint_map='{keypoints:{cube:[cube_x,cube_y]},robot:[ee_x,ee_y]}'"


@dataclass(frozen=True)
class KeypointMap:
    """Which named columns of a LeRobot dataset's ``observation.state`` are keypoints, and which are the robot's.

    ``columns`` holds each keypoint's columns (its x, y[, z]: ``D`` of them, the same ``D``, 2 or 3, for every
    keypoint) in kpflow's order, the robot's ``robot`` keypoints last (kpflow's layout: ``model.processor.origin=-1`` is the
    robot); ``names`` names each keypoint. Other columns of the state are not read. From a config
    (:meth:`from_config`, ``data.keypoint_map``)::

        keypoint_map:
          keypoints:                   # each keypoint's columns, by name: {name: [x, y(, z)], ...} or [[x, y], ...]
            cube: [cube_x, cube_y]
            target: [target_x, target_y]
          robot: [ee_x, ee_y]          # the robot's keypoint, placed last (several: [[l_x, l_y], [r_x, r_y]])
    """

    columns: tuple[tuple[str, ...], ...]
    names: tuple[str, ...]
    robot: int = 0

    def __post_init__(self) -> None:
        if not self.columns:
            raise ValueError(
                f"keypoint_map maps no keypoints: give keypoints and robot columns, e.g. {MAP_EXAMPLE} ({MAP_HELP})"
            )
        if len(self.names) != len(self.columns) or not 0 <= self.robot <= len(self.columns):
            raise ValueError(
                f"keypoint_map: {len(self.columns)} keypoints need as many names ({len(self.names)} given) and at most that many robot ones"
            )
        dims = {len(c) for c in self.columns}
        if len(dims) != 1 or not dims <= {2, 3}:
            given = ", ".join(f"{n}: {list(c)}" for n, c in zip(self.names, self.columns))
            raise ValueError(
                f"keypoint_map: every keypoint needs the same number of columns, 2 (x, y) or 3 (x, y, z); it gives {given}"
            )
        if len(set(self.names)) != len(self.names):
            raise ValueError(
                f"keypoint_map names two keypoints alike: {list(self.names)} (the robot's are robot, robot0, robot1, ...)"
            )
        flat = self.flat_columns
        if len(set(flat)) != len(flat):
            raise ValueError(
                f"keypoint_map names the columns {sorted({c for c in flat if flat.count(c) > 1})} more than once: each column is one value of one keypoint"
            )

    @classmethod
    def from_config(cls, spec: KeypointMap | Mapping) -> KeypointMap:
        """The map of a config node ``{keypoints: {name: [x, y(, z)], ...} | [[x, y], ...], robot: [x, y] | [[x, y], ...]}``
        (``robot`` may be left out: no robot keypoint)."""
        if isinstance(spec, KeypointMap):
            return spec
        if not isinstance(spec, Mapping) or "keypoints" not in spec or set(spec) - {"keypoints", "robot"}:
            found = f"the keys {sorted(map(str, spec))}" if isinstance(spec, Mapping) else f"a {type(spec).__name__}"
            raise ValueError(
                f"keypoint_map takes the keys keypoints and robot, e.g. {MAP_EXAMPLE}; it has {found} ({MAP_HELP})"
            )
        named = _keypoint_columns(spec["keypoints"], "keypoints")
        robot = _keypoint_columns(spec.get("robot") or [], "robot")
        keypoints = named + robot
        return cls(tuple(c for _, c in keypoints), tuple(n for n, _ in keypoints), len(robot))

    @property
    def dim(self) -> int:
        """``D``: each keypoint's columns."""
        return len(self.columns[0])

    @property
    def flat_columns(self) -> list[str]:
        return [c for cols in self.columns for c in cols]

    def indices(self, names, where: str) -> np.ndarray:
        """Where each keypoint's columns are among a state's column ``names`` (any of :func:`flat_names`' spellings):
        ``[K, D]`` ints. ``ValueError`` naming the columns the map expected and the state lacks, and those it has."""
        found = flat_names(names)
        if not isinstance(found, list) or not found:
            raise ValueError(f"{where} has no column names in meta/info.json, and keypoint_map picks columns by name: "
                             f"add its names there (features.observation.state.names: [..., ...])")  # fmt: skip
        found = [str(n) for n in found]
        if missing := [c for c in self.flat_columns if c not in found]:
            raise ValueError(
                f"{where} has no columns {missing} that keypoint_map names; its columns are {found}: correct data.keypoint_map ({MAP_HELP})"
            )
        if repeated := sorted({c for c in self.flat_columns if found.count(c) > 1}):
            raise ValueError(
                f"{where} names more than one column {repeated}: keypoint_map cannot tell which one is meant"
            )
        return np.array([[found.index(c) for c in cols] for cols in self.columns], np.int64)

    def apply(self, state: np.ndarray, names, where: str = "observation.state") -> np.ndarray:
        """``state [..., F]`` (columns named ``names``, the dataset's order) as keypoints ``[..., K, D]``: what a policy
        trained through this map observes, e.g. on the robot."""
        state, index = np.asarray(state), self.indices(names, where)
        if state.shape[-1] != len(flat_names(names)):
            raise ValueError(f"{where}: {state.shape[-1]} values per frame but {len(flat_names(names))} column names")
        return state[..., index]


def _keypoint_columns(spec, key: str) -> list[tuple[str, tuple[str, ...]]]:
    """``(name, columns)`` per keypoint of a config's ``keypoints`` or ``robot``: ``{name: [x, y(, z)], ...}``, a list of
    such column lists, or (``robot`` only) one keypoint's column list."""

    def is_list(value) -> bool:
        return isinstance(value, Sequence) and not isinstance(value, str)

    def columns(value, name: str) -> tuple[str, ...]:
        if not is_list(value) or not all(isinstance(c, str) for c in value):
            raise ValueError(
                f"keypoint_map.{key}: {name} must be a list of its 2 or 3 column names (x, y[, z]); got {value!r}"
            )
        return tuple(value)

    if isinstance(spec, Mapping):
        return [(str(name), columns(value, str(name))) for name, value in spec.items()]
    if is_list(spec) and spec and all(isinstance(c, str) for c in spec):
        if key == "robot":
            return [("robot", tuple(spec))]
        raise ValueError(f"keypoint_map.keypoints lists column names {list(spec)}: give each keypoint its own list, "
                         f"[[a_x, a_y], [b_x, b_y]], or name them, {{a: [a_x, a_y], b: [b_x, b_y]}}")  # fmt: skip
    if is_list(spec):
        prefix = "robot" if key == "robot" else "k"
        return [(f"{prefix}{i}", columns(value, f"{key}[{i}]")) for i, value in enumerate(spec)]
    raise ValueError(
        f"keypoint_map.{key} must map names to column lists or list column lists, e.g. {MAP_EXAMPLE}; got {spec!r}"
    )


def _keypoints_shaped(flat: np.ndarray, names, field: str, where: str) -> np.ndarray:
    """``flat [T, F]`` for store field ``field``; kpflow's keypoint names reshape it to ``[T, K, D]``. Names that repeat,
    or keypoint names out of order, are refused (they would import as a different layout)."""
    names = flat_names(names)
    if isinstance(names, list) and len(set(map(str, names))) != len(names):
        repeated = sorted({str(n) for n in names if names.count(n) > 1})
        raise ValueError(f"{where} names its values with repeats ({repeated[:3]}): each value needs its own name")
    if (
        field != "keypoints"
        or not isinstance(names, list)
        or not any(re.fullmatch(r"k\d+\.[xyz]", str(n)) for n in names)
    ):
        return flat
    layout = keypoint_layout(names)
    if layout is None or layout[0] * layout[1] != flat.shape[1]:
        raise ValueError(
            f"{where}: its keypoint names are not k0.x, k0.y, ... in order for its {flat.shape[1]} values: {names[:6]!r}..."
        )
    return flat.reshape(len(flat), *layout)


def _names(field: str, shape: tuple[int, ...]) -> list[str] | None:
    if field == "keypoints" and len(shape) == 2 and shape[1] <= len(AXES):
        return [f"k{k}.{AXES[d]}" for k in range(shape[0]) for d in range(shape[1])]
    return None


def _stats(values: np.ndarray) -> dict[str, list]:
    """LeRobot's per-feature statistics of ``values [N, F]`` (quantiles exact here, not from histograms)."""
    values = values.astype(np.float64)
    out = {"min": values.min(0), "max": values.max(0), "mean": values.mean(0), "std": values.std(0)}
    out |= {f"q{round(100 * q):02d}": np.quantile(values, q, axis=0) for q in QUANTILES}
    return {k: v.tolist() for k, v in out.items()} | {"count": [len(values)]}


def _tasks_table(tasks: list[str]) -> pa.Table:
    """``meta/tasks.parquet`` as pandas writes it (lerobot reads it with pandas: the task string is the index)."""
    table = pa.table(
        {"task_index": pa.array(range(len(tasks)), pa.int64()), "__index_level_0__": pa.array(tasks, pa.string())}
    )
    pandas = {"index_columns": ["__index_level_0__"],
              "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
              "columns": [{"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64", "metadata": None},
                          {"name": None, "field_name": "__index_level_0__", "pandas_type": "unicode", "numpy_type": "object", "metadata": None}],
              "creator": {"library": "pyarrow", "version": pa.__version__}, "pandas_version": "2.3.3"}  # fmt: skip
    return table.replace_schema_metadata({b"pandas": json.dumps(pandas).encode()})


def _vector_column(values: np.ndarray) -> pa.FixedSizeListArray:
    flat = np.ascontiguousarray(values, dtype=np.float32).reshape(len(values), -1)
    return pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), flat.shape[1])


def export_lerobot(
    store: EpisodeStore,
    root: str | Path,
    fps: float = 10.0,
    task: str = "",
    robot_type: str | None = None,
    fields: tuple[str, ...] | None = None,
    data_files_size_in_mb: float = 100.0,
    chunks_size: int = 1000,
    overwrite: bool = False,
) -> Path:
    """Write ``store``'s episodes (``fields``: all of them by default) as a LeRobot v3.0 dataset at ``root``.

    ``task`` is every episode's task description. Raises ``FileExistsError`` if ``root`` exists (unless
    ``overwrite``), ``ValueError`` for an empty store or an unknown field.
    """
    fields = tuple(store.fields) if fields is None else tuple(fields)
    if store.n_episodes == 0:
        raise ValueError(f"{store.path} holds no episodes to export")
    if unknown := sorted(set(fields) - set(store.fields)):
        raise ValueError(f"fields {unknown} are not in the store (it has {list(store.fields)})")
    if not fps > 0 or chunks_size < 1 or not data_files_size_in_mb > 0:
        raise ValueError(
            f"fps, chunks_size and data_files_size_in_mb must be positive; got {fps}, {chunks_size}, {data_files_size_in_mb}"
        )
    arrays = {f: store.field(f) for f in fields}
    features = {
        feature_name(f): {"dtype": "float32", "shape": [int(np.prod(a.shape[1:]))], "names": _names(f, a.shape[1:])}
        for f, a in arrays.items()
    }
    ends = store.episode_ends
    starts = np.concatenate([[0], ends[:-1]])
    index = np.arange(int(ends[-1]))
    episode_index = np.searchsorted(ends, index, side="right")
    frame_index = index - starts[episode_index]
    # every column once, over all frames, as stored: each file and each episode's statistics are slices of these
    columns = {feature_name(f): a.reshape(len(a), -1).astype(np.float32) for f, a in arrays.items()}
    columns |= {"timestamp": (frame_index / fps).astype(np.float32), "frame_index": frame_index, "episode_index": episode_index,
                "index": index, "task_index": np.zeros(len(index), np.int64)}  # fmt: skip
    row_bytes = sum(c.dtype.itemsize * (c.shape[1] if c.ndim == 2 else 1) for c in columns.values())
    # consecutive episodes share a file until it would reach data_files_size_in_mb (lerobot's rule)
    files, episode_file, (chunk, file), first = [], [], (0, 0), 0
    for a, b in zip(starts, ends):
        if a > first and (b - first) * row_bytes >= data_files_size_in_mb * 2**20:
            files.append((chunk, file, first, a))
            chunk, file, first = (chunk + 1, 0, a) if file == chunks_size - 1 else (chunk, file + 1, a)
        episode_file.append((chunk, file))
    files.append((chunk, file, first, int(ends[-1])))
    with atomic_dir(root, overwrite=overwrite) as tmp:
        for c, f, a, b in files:
            table = pa.table(
                {name: _vector_column(v[a:b]) if v.ndim == 2 else pa.array(v[a:b]) for name, v in columns.items()}
            )
            path = tmp / DATA_PATH.format(chunk_index=c, file_index=f)
            path.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, path)
        episodes: dict[str, list] = {"episode_index": list(range(len(ends))), "tasks": [[task]] * len(ends), "length": (ends - starts).tolist(),
                                     "data/chunk_index": [c for c, _ in episode_file], "data/file_index": [f for _, f in episode_file],
                                     "dataset_from_index": starts.tolist(), "dataset_to_index": ends.tolist(),
                                     "meta/episodes/chunk_index": [0] * len(ends), "meta/episodes/file_index": [0] * len(ends)}  # fmt: skip
        for name, values in columns.items():
            per_episode = [_stats(values[a:b].reshape(b - a, -1)) for a, b in zip(starts, ends)]
            for stat in per_episode[0]:
                episodes[f"stats/{name}/{stat}"] = [s[stat] for s in per_episode]
        path = tmp / EPISODES_PATH.format(chunk_index=0, file_index=0)
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table(episodes), path)
        pq.write_table(_tasks_table([task]), tmp / "meta" / "tasks.parquet")
        stats = {name: _stats(values.reshape(len(index), -1)) for name, values in columns.items()}
        (tmp / "meta" / "stats.json").write_text(json.dumps(stats, indent=2))
        info = {
            "codebase_version": CODEBASE_VERSION, "robot_type": robot_type, "total_episodes": int(store.n_episodes),
            "total_frames": int(ends[-1]), "total_tasks": 1, "chunks_size": int(chunks_size),
            "data_files_size_in_mb": data_files_size_in_mb, "video_files_size_in_mb": 200, "fps": fps,
            "splits": {"train": f"0:{store.n_episodes}"}, "data_path": DATA_PATH, "video_path": None,
            "features": {**features, **DEFAULT_FEATURES},
        }  # fmt: skip
        (tmp / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    return Path(root)


def read_info(root: str | Path) -> dict:
    """``meta/info.json`` of the LeRobot dataset at ``root``; ``FileNotFoundError`` or ``ValueError`` naming the
    problem when it is missing, not v3.0 or lacks what a reader needs."""
    path = Path(root) / "meta" / "info.json"
    if not path.is_file():
        raise FileNotFoundError(f"{root} is not a LeRobot dataset: no meta/info.json")
    try:
        info = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not JSON ({e})") from None
    if not str(info.get("codebase_version", "")).startswith("v3."):
        raise ValueError(f"{root} is a LeRobot dataset of format {info.get('codebase_version')!r}; kpflow reads v3.x")
    if missing := sorted({"features", "data_path", "total_episodes", "total_frames", "fps"} - set(info)):
        raise ValueError(f"{path} lacks {missing}")
    return info


def import_lerobot(
    root: str | Path,
    store_path: str | Path,
    columns: Mapping[str, str] | None = None,
    keypoint_map: KeypointMap | Mapping | None = None,
) -> EpisodeStore:
    """The state/action columns of the LeRobot v3 dataset at ``root`` as a new :class:`EpisodeStore` at
    ``store_path``, one episode per ``episode_index`` in order.

    ``columns`` maps a feature to a store field (default: ``observation.state -> keypoints`` when its names are
    kpflow's ``k<i>.<axis>`` or a ``keypoint_map`` is given, else ``-> state``; ``action -> action``). A keypoint
    feature is reshaped to ``[T, K, D]``: by its ``k<i>.<axis>`` names, or with ``keypoint_map``
    (:class:`KeypointMap`) its columns picked by name, the robot's keypoints last. Raises ``FileExistsError`` if
    ``store_path`` exists and ``ValueError`` naming the problem for a dataset that does not hold what it says.
    """
    root, store_path = Path(root), Path(store_path)
    if store_path.exists():
        raise FileExistsError(f"{store_path} exists already: import into a new store")
    info = read_info(root)
    features = info["features"]
    keypoint_map = None if keypoint_map is None else KeypointMap.from_config(keypoint_map)
    if columns is None:
        layout = keypoint_map or keypoint_layout(features.get("observation.state", {}).get("names"))
        columns = {"observation.state": "keypoints" if layout else "state", "action": "action"}
    if unknown := sorted(set(columns) - set(features)):
        raise ValueError(f"{root} has no features {unknown} (it has {sorted(features)})")
    files = sorted((root / "data").glob("*/*.parquet"))
    if not files:
        raise ValueError(f"{root} has no data files (data/*/*.parquet)")
    widths = {feature: _width(features[feature], f"{root}: feature {feature}") for feature in columns}
    picked = [feature for feature, name in columns.items() if name == "keypoints" and keypoint_map is not None]
    for feature in picked:  # the mapped columns are there, before any data file is read
        keypoint_map.indices(features[feature].get("names"), f"{root}: feature {feature}")
    if int(info["total_frames"]) < 1:
        raise ValueError(
            f"{root}: info.json declares {info['total_frames']} frames: a dataset to import needs at least one"
        )
    check_parquet_rows(files, int(info["total_frames"]), {**widths, "episode_index": 1, "frame_index": 1}, str(root))
    table = pa.concat_tables([read_parquet(f, [*columns, "episode_index", "frame_index"], str(root)) for f in files])
    episode = table["episode_index"].to_numpy()
    order = np.lexsort((table["frame_index"].to_numpy(), episode))
    values = {}
    for feature, name in columns.items():
        flat = np.asarray(table[feature].combine_chunks().flatten().to_numpy(), np.float32).reshape(table.num_rows, -1)[
            order
        ]
        shape = features[feature]["shape"]
        if flat.shape[1] != int(np.prod(shape)):
            raise ValueError(
                f"{root}: feature {feature} has shape {shape} in info.json but {flat.shape[1]} values per frame"
            )
        if feature in picked:
            values[name] = keypoint_map.apply(flat, features[feature].get("names"), f"{root}: feature {feature}")
        else:
            values[name] = _keypoints_shaped(flat, features[feature].get("names"), name, f"{root}: feature {feature}")
    episode = episode[order]
    bounds = np.flatnonzero(np.diff(episode)) + 1
    if len(bounds) + 1 != info["total_episodes"]:
        raise ValueError(f"{root}: info.json says {info['total_episodes']} episodes, the data holds {len(bounds) + 1}")
    with atomic_dir(store_path) as tmp, EpisodeStore(tmp, mode="a") as store:  # all of it or nothing at store_path
        for a, b in zip(np.concatenate([[0], bounds]), np.concatenate([bounds, [len(episode)]])):
            store.add_episode({name: v[a:b] for name, v in values.items()})
    return EpisodeStore(store_path)


def open_lerobot(root: str | Path, keypoint_map: KeypointMap | Mapping | None = None) -> EpisodeStore:
    """The LeRobot v3 dataset at ``root`` as a read-only :class:`EpisodeStore` in a temporary folder (imported with
    :func:`import_lerobot`'s default columns and ``keypoint_map``, removed when the store is garbage-collected or the
    process exits): what a datamodule reads a LeRobot dataset through, without writing beside it."""
    import shutil
    import tempfile
    import weakref

    folder = Path(tempfile.mkdtemp(prefix="kpflow-lerobot-"))
    try:
        import_lerobot(root, folder / "episodes.zarr", keypoint_map=keypoint_map)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    store = EpisodeStore(folder / "episodes.zarr", mode="r")
    weakref.finalize(store, shutil.rmtree, folder, True)
    return store


def naming_help(root: str | Path, field: str, fields: list[str]) -> str:
    """Why the LeRobot dataset at ``root`` gave no store field ``field`` (it gave ``fields``): the names kpflow
    expected, the names the dataset has, and what to change."""
    if field != "keypoints":
        return (f"{root}: the LeRobot dataset gave no field {field!r} (it gave {fields}): kpflow reads its observation.state as "
                f"'keypoints' (or as 'state' when no keypoint names or data.keypoint_map say its layout) and its action as 'action'; "
                f"name one of {fields} with data.obs_key / data.action_key")  # fmt: skip
    features = read_info(root)["features"]
    found = flat_names(features.get("observation.state", {}).get("names"))
    shown = found[:8] if isinstance(found, list) else found
    return (
        f"{root}: the LeRobot dataset gave no field {field!r} (it gave {fields}). kpflow reads keypoints from feature "
        f"observation.state named k0.x, k0.y[, k0.z], k1.x, ... (every keypoint's 2 or 3 axes, in that order); its "
        f"observation.state is named {shown!r}{'...' if isinstance(found, list) and len(found) > 8 else ''}. Say which of "
        f"its columns are keypoints and which the robot's with data.keypoint_map, e.g. {MAP_EXAMPLE} ({MAP_HELP}), rename "
        f"them so in meta/info.json, or read the flat state as it is: data.obs_key=state"
    )


def is_lerobot(root: str | Path) -> bool:
    """Whether ``root`` is a LeRobot dataset folder (it holds ``meta/info.json``)."""
    return (Path(root) / "meta" / "info.json").is_file()
