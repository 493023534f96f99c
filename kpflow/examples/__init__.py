"""The examples the README and the guides use, installed with kpflow so that they work without a clone.

Scripts, each runnable as ``python -m kpflow.examples.<name>``:

- ``connect``: a client asks a running policy server for one action chunk (also the command ``kpflow-connect``);
- ``train_on_store``: a K-CFM trained on an episode store from Python, and acting once loaded back;
- ``transport_trajectory``: a demonstration carried into a new scene through ILWR and GP maps (the transport
  tutorial's code).

Templates, project folders to start from, copied by ``kpflow-example NAME DIR`` (:func:`copy_template`; with no
arguments it lists them): ``reach_task``, a task of your own with a simulator (the own-task tutorial's).
"""

from __future__ import annotations

import argparse
import ast
import os
import shutil
from pathlib import Path

TEMPLATES = Path(__file__).resolve().parent / "templates"
_SKIPPED = shutil.ignore_patterns("__pycache__", "*.pyc")


def _summary(folder: Path) -> str:
    """The first line of a template's description: the docstring of its package or, failing that, of a script."""
    for path in sorted(folder.glob("*/__init__.py")) + sorted(folder.glob("*.py")):
        doc = ast.get_docstring(ast.parse(path.read_text()))
        if doc:
            return " ".join(doc.replace("``", "").split()).split(". ")[0].rstrip(".")
    return ""


def templates() -> dict[str, str]:
    """The templates ``kpflow-example`` can copy: name -> what it is (one line)."""
    return {
        p.name: _summary(p) for p in sorted(TEMPLATES.iterdir()) if p.is_dir() and not p.name.startswith(("_", "."))
    }


def copy_template(name: str, dest: str | Path) -> Path:
    """Copy template ``name`` into the folder ``dest`` (created; it may exist if empty) and return ``dest``.

    Raises:
        ValueError: no template ``name`` (the message lists them); ``dest`` is a file, a symbolic link to nothing or
            a folder that is not empty (nothing is overwritten); or it cannot be written (a read-only folder, a
            full disk), when what was copied is removed again. Each message names ``dest`` and the fix.
    """
    known = templates()
    if name not in known:
        raise ValueError(
            f"no template {name!r}: kpflow-example copies one of {', '.join(known)} (kpflow-example lists them)"
        )
    dest = Path(dest)
    again = f"name a new or empty folder you can write to (kpflow-example {name} DIR)"
    if dest.is_symlink() and not dest.exists():
        raise ValueError(f"{dest} is a symbolic link to {os.readlink(dest)}, which does not exist: {again}")
    if dest.exists() and not dest.is_dir():
        raise ValueError(f"{dest} is a file: {again}")
    if dest.is_dir() and any(dest.iterdir()):
        raise ValueError(f"{dest} is not empty, so nothing was copied: {again}")
    existed = dest.is_dir()
    try:
        shutil.copytree(TEMPLATES / name, dest, ignore=_SKIPPED, dirs_exist_ok=True)
    except OSError as e:
        if existed:  # leave the empty folder it was, not part of a template
            for entry in list(dest.iterdir()) if dest.is_dir() else []:
                shutil.rmtree(entry, ignore_errors=True) if entry.is_dir() and not entry.is_symlink() else entry.unlink(
                    missing_ok=True
                )
        else:
            shutil.rmtree(dest, ignore_errors=True)
        reason = e.strerror or "some of its files could not be written"  # shutil.Error: one (src, dst, why) per file
        raise ValueError(f"{dest} could not be written ({reason}), so nothing was copied: {again}") from None
    return dest


def main(argv: list[str] | None = None) -> None:
    """``kpflow-example NAME DIR``: copy a template into DIR; ``kpflow-example`` alone lists the templates."""
    from kpflow.utils.errors import command

    parser = argparse.ArgumentParser(
        prog="kpflow-example",
        description="Copy one of kpflow's project templates into a folder (no arguments: list them).",
    )
    parser.add_argument("name", nargs="?", help="the template, e.g. reach_task")
    parser.add_argument("dir", nargs="?", help="the folder to create (new or empty)")
    args = parser.parse_args(argv)

    @command
    def run() -> None:
        if args.name is None:
            print("templates (kpflow-example NAME DIR copies one):")
            for name, summary in templates().items():
                print(f"  {name:<12} {summary}")
        elif args.dir is None:
            parser.error(f"name the folder to copy {args.name!r} into: kpflow-example {args.name} DIR")
        else:
            dest = copy_template(args.name, args.dir)
            held = ", ".join(p.name + ("/" if p.is_dir() else "") for p in sorted(dest.iterdir()))
            print(f"copied the {args.name} template into {dest} ({held})")

    run()
