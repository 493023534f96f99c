"""Where kpflow keeps the data it makes for you (the expert demonstrations a config collects on first use), so that a
command never writes ``data/`` into whatever folder it was run from: ``${kpflow_data:NAME}`` in a config value is
``data_dir() / NAME``.

:func:`data_dir` is, in order, ``$KPFLOW_DATA_DIR`` when set; the clone's ``data/`` when kpflow runs from a clone
(where ``make demo`` has always kept it); else the user's cache, ``~/.cache/kpflow/data``
(``$XDG_CACHE_HOME/kpflow/data`` when that is set). The collection says where it writes.
"""

from __future__ import annotations

import os
from pathlib import Path

from kpflow.utils.releases import cache_dir, clone_dir

ENV = "KPFLOW_DATA_DIR"


def data_dir() -> Path:
    """The folder collected data goes into (module docstring); ``ValueError`` naming ``$KPFLOW_DATA_DIR``
    when it names something that is not a folder."""
    if env := os.environ.get(ENV):
        path = Path(env).expanduser()
        if path.exists() and not path.is_dir():
            raise ValueError(
                f"{ENV}={env} is not a folder (it is a file): point {ENV} at a folder, which is created if missing, or unset it"
            )
        return path
    clone = clone_dir()
    return clone / "data" if clone is not None else cache_dir().parent / "data"


def register_resolver() -> None:
    """Register the OmegaConf resolver ``kpflow_data`` (``${kpflow_data:NAME}`` -> ``data_dir() / NAME``), once."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("kpflow_data"):
        OmegaConf.register_new_resolver("kpflow_data", lambda name: str(data_dir() / str(name)))
