"""Reading npz, YAML and parquet files so that no file can run code or make kpflow allocate more than it could hold.

Each reader checks what a file declares before decoding its payload, and raises ``ValueError`` naming the file and
the entry that is refused:

- **npz** (:func:`read_npz`): numpy's ``allow_pickle=False`` (an object array is refused, not unpickled); each
  member's ``.npy`` header must declare a plain numeric dtype and exactly the bytes the zip entry holds, and the
  entry may expand to at most :data:`MAX_DEFLATE_RATIO` times its stored size plus :data:`EXPANSION_SLACK` (kpflow's
  own arrays compress 2-7 times; runs of one integer, a source index's episode ids, ~270 times over a few hundred
  kB), so that a small file cannot declare gigabytes that numpy would allocate before reading. A checkpoint's zip
  entries are held to the same bound (:func:`check_zip_expansion`; ``torch.save`` stores them uncompressed).
- **YAML** (:func:`read_yaml`): at most :data:`MAX_YAML_BYTES`, and no anchors or aliases (an alias-expanding "billion
  laughs" document is a few hundred bytes that OmegaConf would expand into gigabytes); parsed by OmegaConf, whose
  loader is PyYAML's safe one (no Python tags).
- **parquet** (:func:`check_parquet_rows`): the files' footers must declare exactly the rows the dataset says it
  has, and columns of at most the values per row its features give and a bounded size per row, before any column
  is decompressed. pyarrow builds only
  arrow arrays from parquet, never Python objects, so nothing in it can run code.

Checkpoints have their own reader (:mod:`kpflow.utils.checkpoint`, ``torch.load(weights_only=True)``), and so do zarr
stores (:mod:`kpflow.data.zarr_checks`). kpflow writes hdf5 (robomimic's layout) but never reads it.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Iterable

import numpy as np

#: how many times its stored size a compressed zip member may expand, beyond :data:`EXPANSION_SLACK`.
MAX_DEFLATE_RATIO = 64
#: bytes any zip member may expand to whatever its ratio (small arrays of repeated values compress without bound).
EXPANSION_SLACK = 1 << 20
#: the largest YAML file read (run configs are a few kB).
MAX_YAML_BYTES = 1 << 20
_NPY_KINDS = "biuf"


def read_npz(path: str | Path, names: Iterable[str], optional: Iterable[str] = ()) -> dict[str, np.ndarray]:
    """The arrays ``names`` of the npz file at ``path``, and those of ``optional`` it holds, checked first (module
    docstring).

    Raises ``FileNotFoundError`` for a missing file and ``ValueError`` naming the file and member otherwise (not a
    zip, a missing member, a refused dtype, a header that does not match the member's size)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no file at {path}")
    names = list(names)
    try:
        with zipfile.ZipFile(path) as archive:
            held = set(archive.namelist())
            names += [name for name in optional if f"{name}.npy" in held]
            for name in names:
                _check_member(archive, name, path)
        with np.load(path, allow_pickle=False) as f:
            return {name: f[name] for name in names}
    except (zipfile.BadZipFile, OSError, EOFError) as e:
        raise ValueError(f"{path} is not a readable npz file ({type(e).__name__}: {e})") from None


def _check_member(archive: zipfile.ZipFile, name: str, path: Path) -> None:
    """Raise ``ValueError`` unless member ``name``.npy declares a numeric array whose bytes are what the entry holds."""
    try:
        info = archive.getinfo(f"{name}.npy")
    except KeyError:
        raise ValueError(
            f"{path} has no array {name!r} (it has {sorted(n.removesuffix('.npy') for n in archive.namelist())})"
        ) from None
    _check_ratio(info, path, f"array {name!r}")
    with archive.open(info) as member:
        try:
            version = np.lib.format.read_magic(member)
            if version not in ((1, 0), (2, 0)):  # 3.0 exists for structured dtypes with unicode names only
                raise ValueError(f"format version {version} is not read")
            read_header = (
                np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            )
            shape, _, dtype = read_header(member)
        except ValueError as e:
            raise ValueError(f"{path}: array {name!r} has a damaged header ({e})") from None
        header = member.tell()
    if dtype.kind not in _NPY_KINDS or dtype.fields is not None or dtype.subdtype is not None:
        raise ValueError(f"{path}: array {name!r} has dtype {dtype}; kpflow reads bool, integer and float arrays")
    declared = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if header + declared != info.file_size:
        raise ValueError(
            f"{path}: array {name!r} declares {shape} x {dtype} ({declared} bytes) but holds {info.file_size - header}"
        )


def _check_ratio(info: zipfile.ZipInfo, path: Path, what: str) -> None:
    if (
        info.compress_type != zipfile.ZIP_STORED
        and info.file_size > MAX_DEFLATE_RATIO * info.compress_size + EXPANSION_SLACK
    ):
        raise ValueError(
            f"{path}: {what} claims {info.file_size} bytes from {info.compress_size} stored, beyond {MAX_DEFLATE_RATIO} times "
            f"plus {EXPANSION_SLACK} bytes; refusing to decompress it"
        )


def check_zip_expansion(path: str | Path) -> None:
    """Raise ``ValueError`` naming ``path`` and the member when a zip file (a checkpoint, an npz) has a compressed
    member that would expand beyond the bound of the module docstring; a file that is not a zip is left to its
    reader."""
    path = Path(path)
    if not zipfile.is_zipfile(path):
        return
    with zipfile.ZipFile(path) as archive:
        for info in archive.infolist():
            _check_ratio(info, path, f"member {info.filename!r}")


def read_yaml(path: str | Path):
    """The YAML file at ``path`` as an OmegaConf object, checked first (module docstring)."""
    import yaml
    from omegaconf import OmegaConf

    path = Path(path)
    size = path.stat().st_size
    if size > MAX_YAML_BYTES:
        raise ValueError(f"{path} is {size} bytes; kpflow reads YAML files of at most {MAX_YAML_BYTES >> 20} MiB")
    text = path.read_text()
    try:
        for event in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None):
                raise ValueError(
                    f"{path} uses YAML anchors or aliases, which kpflow refuses (they can expand without bound)"
                )
    except yaml.YAMLError as e:
        raise ValueError(f"{path} is not valid YAML ({e})") from None
    return OmegaConf.create(text)


def parquet_metadata(path: Path, where: str):
    """The footer of parquet file ``path``; ``ValueError`` naming the file (and ``where``) when it is not parquet."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        return pq.ParquetFile(path).metadata
    except (pa.ArrowException, OSError) as e:
        raise ValueError(f"{where}: {path} is not a readable parquet file ({e})") from None


def read_parquet(path: Path, columns: list[str], where: str):
    """Columns ``columns`` of parquet file ``path`` (a pyarrow table); ``ValueError`` naming the file for one that
    does not read (a schema with duplicated names, a damaged page, a missing column)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        return pq.read_table(path, columns=columns)
    except (pa.ArrowException, OSError, KeyError) as e:
        raise ValueError(f"{where}: {path} does not read as parquet with columns {columns} ({e})") from None


def check_parquet_rows(files: list[Path], rows: int, columns: dict[str, int], where: str) -> None:
    """Raise ``ValueError`` unless the parquet ``files`` declare ``rows`` rows in all and, for each column of
    ``columns`` (name -> values per row), at most that many values per row (a list column's value count, which
    run-length encoding lets a few kB declare by the million) and at most 16 bytes per value and row uncompressed
    (float32 or int64 values plus list offsets and validity), read from their footers only; and unless each file holds at least
    ``1 / MAX_DEFLATE_RATIO`` of the float32 values it declares (beyond :data:`EXPANSION_SLACK`): a few kB cannot
    declare millions of frames that decoding would allocate (dictionary and run-length encodings shrink what a
    footer says is uncompressed, so the file's own size is the bound)."""

    total = 0
    for f in files:
        meta = parquet_metadata(f, where)
        total += meta.num_rows
        need, size = 4 * meta.num_rows * sum(columns.values()), Path(f).stat().st_size
        if need > MAX_DEFLATE_RATIO * size + EXPANSION_SLACK:
            raise ValueError(
                f"{where}: {Path(f).name} declares {meta.num_rows} frames of {sum(columns.values())} values ({need} bytes) in a "
                f"{size}-byte file, beyond {MAX_DEFLATE_RATIO} times its size; refusing to decode it"
            )
        for g in range(meta.num_row_groups):
            group = meta.row_group(g)
            for c in range(group.num_columns):
                column = group.column(c)
                name = column.path_in_schema.split(".list.")[0]  # a list column's values are "<name>.list.element"
                width = columns.get(name)
                if (
                    width is not None and column.num_values > (width + 1) * group.num_rows
                ):  # + 1: a null row's one level
                    raise ValueError(
                        f"{where}: {f.name} declares {column.num_values} values in column {name} over {group.num_rows} rows, "
                        f"more than the {width} per row the dataset's features give; refusing to decode it"
                    )
                if width is not None and column.total_uncompressed_size > 16 * width * group.num_rows + 65536:
                    raise ValueError(
                        f"{where}: {f.name} declares {column.total_uncompressed_size} bytes for column {name} over "
                        f"{group.num_rows} rows ({width} values each); refusing to decompress it"
                    )
    if total != rows:
        raise ValueError(f"{where}: info.json says {rows} frames, the data files declare {total}")
