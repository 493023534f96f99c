"""Released files by name: ``release:NAME`` wherever a checkpoint is named, ``${release:NAME}`` in any config value.

kpflow's released checkpoints (and the stores and source indices beside them) ship inside the package, in
``kpflow/release/`` (package data: an installed wheel has them; a clone's ``release/`` is a link to that folder).
:func:`release_path` finds one by name, looking in order in

1. ``$KPFLOW_RELEASE_DIR``, when set (e.g. files of another version, or one's own releases);
2. the package's ``kpflow/release/``;
3. the user's cache, ``~/.cache/kpflow/release`` (``$XDG_CACHE_HOME/kpflow/release`` when that is set).

A name without a suffix is a checkpoint (``pusht_standard_fast`` is ``pusht_standard_fast.ckpt``); any other file
is named whole (``pusht_table1_35_corrected.zarr``). Where it is in none of them, the error says where it looked and
which releases this version has. Nothing is downloaded.

:func:`resolve_release` is what every checkpoint reader calls (:func:`kpflow.utils.checkpoint.read_checkpoint`,
hence ``kpflow.load_policy("release:pusht_standard_fast")``, ``policy.checkpoint=release:...``, ``kpflow-release
src=release:...``; :func:`kpflow.serving.deployment.load_deployment`, hence ``kpflow-serve
checkpoint=release:...``); :func:`register_resolver` adds the OmegaConf resolver ``release`` for any other config
value (``data.path='${release:pusht_table1_35_corrected.zarr}'``).
"""

from __future__ import annotations

import os
from importlib.metadata import version
from pathlib import Path

PREFIX = "release:"
#: the folder looked in first
ENV = "KPFLOW_RELEASE_DIR"
#: the package's own releases (package data, kpflow/release/)
PACKAGE_DIR = Path(__file__).resolve().parents[1] / "release"


def cache_dir() -> Path:
    """The user's cache of released files: ``$XDG_CACHE_HOME/kpflow/release``, by default ``~/.cache/kpflow/release``."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "kpflow" / "release"


def clone_dir() -> Path | None:
    """The clone's root when kpflow runs from a clone (an editable install or the checkout on ``sys.path``), else
    None (an installed wheel)."""
    root = Path(__file__).resolve().parents[2]
    project = root / "pyproject.toml"
    return root if project.is_file() and 'name = "kpflow"' in project.read_text() else None


def package_dir() -> Path:
    """The package's released files, ``kpflow/release/`` (in a clone, ``release/`` links to it)."""
    return PACKAGE_DIR


def search_dirs() -> list[tuple[Path | None, str]]:
    """Where :func:`release_path` looks, in order: (folder or None where there is none, what it is)."""
    env = os.environ.get(ENV)
    return [
        (Path(env).expanduser() if env else None, f"${ENV}" + ("" if env else " (not set)")),
        (package_dir(), "the package's releases"),
        (cache_dir(), "the user cache"),
    ]


def file_name(name: str) -> str:
    """The file ``name`` stands for: ``NAME.ckpt`` for a name without a suffix, else ``name`` itself.

    Raises:
        ValueError: ``name`` is empty or a path (a released file is named by its name alone).
    """
    if not name or name in (".", "..") or "/" in name or "\\" in name:
        raise ValueError(
            f"release:{name} is not a released file's name: give its name alone, e.g. release:pusht_standard_fast"
        )
    return name if Path(name).suffix else f"{name}.ckpt"


def release_path(name: str) -> Path:
    """The path of the released file ``name`` (``pusht_standard_fast`` or ``pusht_table1_35_corrected.zarr``), from
    the first folder of :func:`search_dirs` that holds it.

    Raises:
        FileNotFoundError: no folder holds it; the message names every folder looked in, the released files they
            hold, and where to download it.
        ValueError: ``name`` is not a file name (:func:`file_name`).
    """
    file = file_name(name)
    looked, held = [], set()
    for folder, what in search_dirs():
        if folder is None:
            looked.append(what)
            continue
        if (folder / file).exists():
            return folder / file
        looked.append(f"{folder} ({what}{'' if folder.is_dir() else ', missing'})")
        if folder.is_dir():  # the names release: takes (a source index goes with its checkpoint)
            held |= {
                p.stem if p.suffix == ".ckpt" else p.name for p in folder.iterdir() if p.suffix in (".ckpt", ".zarr")
            }
    there = f"; released there: {', '.join(sorted(held))}" if held else ""
    raise FileNotFoundError(
        f"no released file {file}: looked in {'; '.join(looked)}{there}. kpflow {version('kpflow')} ships its releases "
        f"in the package (kpflow/release/); a file of another version or your own goes into {cache_dir()}/ or a "
        f"folder named by {ENV}"
    )


def resolve_release(path: str | Path) -> Path:
    """``path`` as a path: ``release:NAME`` becomes :func:`release_path` ``(NAME)``, anything else is left as it is."""
    text = str(path)
    return release_path(text[len(PREFIX) :]) if text.startswith(PREFIX) else Path(path)


def register_resolver() -> None:
    """Register the OmegaConf resolver ``release`` (``${release:NAME}`` -> the file's path, as a string), once."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("release"):
        OmegaConf.register_new_resolver("release", lambda name: str(release_path(str(name))))
