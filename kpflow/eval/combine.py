"""A Hydra callback that joins the tables of a multirun sweep into one: ``<sweep dir>/table.md``."""

from __future__ import annotations

from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from kpflow.utils.io import write_text


def combine_tables(sweep_dir: str | Path) -> Path | None:
    """Concatenate the table rows of every ``<sweep_dir>/<job>/results.md`` (header once); None if there are none."""
    sweep_dir = Path(sweep_dir)
    jobs = sorted((p for p in sweep_dir.glob("*/results.md")), key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else 0)
    header, rows = [], []
    for path in jobs:
        lines = [line for line in path.read_text().splitlines() if line.startswith("|")]
        if not lines:
            continue
        header = header or lines[:2]
        rows += lines[2:] if lines[:2] == header else lines
    if not rows:
        return None
    return write_text(sweep_dir / "table.md", "# Combined results\n\n" + "\n".join(header + rows) + "\n")


class CombineTables(Callback):
    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        path = combine_tables(config.hydra.sweep.dir)
        if path is not None:
            print(f"combined table: {path}\n{path.read_text()}")
