"""Every command's ``--help`` in a few lines, fast: read from its config files as they are (the command's header
comment, its own keys and their comments, the experiments it runs with each one's first line), without importing
torch or Hydra. The console scripts start here (:func:`entry`): ``kpflow-train --help`` prints :func:`usage`, and
anything else runs the command (``kpflow.cli.<command>.main``). Hydra's own account of the composed config stays
one flag away: ``kpflow-train --cfg job`` (``--hydra-help`` for Hydra's flags).
"""

from __future__ import annotations

import os
import re
import sys
from importlib import import_module
from pathlib import Path

CONF = Path(__file__).resolve().parents[1] / "conf"
#: the commands with a config file of their own (kpflow/conf/<command>.yaml)
COMMANDS = ("train", "evaluate", "collect", "correct", "generate", "serve", "release", "teleop", "verify", "merge")
_KEY = re.compile(r"^([a-z_][a-z0-9_]*):\s*(.*?)\s+#\s*(.*)$")
_REQUIRED = re.compile(r"^([a-z_][a-z0-9_]*):\s*\?\?\?")
_DEFAULT = re.compile(r"^  - ([a-z_][a-z0-9_/]*):\s*([a-z0-9_]+|null)\b")
HELP_FLAGS = ("-h", "--help")


def _comments(path: Path) -> list[str]:
    """The comment lines at the top of a config file (Hydra's ``@package`` line left out)."""
    out = []
    for line in path.read_text().splitlines():
        if not line.startswith("#"):
            break
        if "@package" not in line:
            out.append(line.lstrip("#").strip())
    return out


def _keys(path: Path) -> list[tuple[str, str, str]]:
    """The top-level keys a config file requires (``???``) or explains in a trailing comment: ``(key, default,
    comment)``; a key holding a mapping is shown as ``key.*``."""
    out = []
    for line in path.read_text().splitlines():
        if (m := _REQUIRED.match(line)) and not _KEY.match(line):
            out.append((m.group(1), "???", "required"))
        elif m := _KEY.match(line):
            key, default, comment = m.groups()
            out.append((f"{key}.*", "", comment) if not default else (key, default, comment))
    return out


def _groups(path: Path) -> list[tuple[str, str, list[str]]]:
    """The config groups a command's defaults list chooses: ``(group, its default, the options installed)``."""
    out, inside = [], False
    for line in path.read_text().splitlines():
        if line.startswith("defaults:"):
            inside = True
        elif inside and not line.startswith("  "):
            break
        elif inside and (m := _DEFAULT.match(line)) and (CONF / m.group(1)).is_dir():
            options = sorted(f.stem for f in (CONF / m.group(1)).glob("*.yaml"))
            out.append((m.group(1), m.group(2), options))
    return out


def _first_sentence(lines: list[str], limit: int = 110) -> str:
    """The first sentence of comment ``lines`` (cut at ``limit`` characters)."""
    text = " ".join(lines)
    end = re.search(r"\.(\s+[A-Z(]|$)", text)
    text = text[: end.start() + 1] if end else text
    return text if len(text) <= limit else text[: limit - 3].rstrip() + "..."


def _trains(path: Path) -> bool:
    """Whether an experiment is one of ``kpflow-train``'s (it chooses a model) rather than ``kpflow-evaluate``'s."""
    return "override /model" in path.read_text()


def experiments(command: str) -> list[tuple[str, str]]:
    """``(name, first line)`` of each experiment ``command`` runs (``train`` or ``evaluate``)."""
    if command not in ("train", "evaluate"):
        return []
    found = []
    for path in sorted((CONF / "experiment").glob("*.yaml")):
        if _trains(path) == (command == "train"):
            found.append((path.stem, _first_sentence(_comments(path))))
    return found


def usage(command: str) -> str:
    """What ``kpflow-<command> --help`` prints (module docstring)."""
    if command not in COMMANDS:
        raise ValueError(f"no command {command!r}; the commands are {', '.join(COMMANDS)}")
    path = CONF / f"{command}.yaml"
    lines = [f"kpflow-{command}: key=value overrides of {path} (Hydra)", ""]
    lines += [f"  {line}" for line in _comments(path)]
    if found := experiments(command):
        lines += ["", "experiments (experiment=NAME):"]
        width = max(len(name) for name, _ in found)
        lines += [f"  {name:<{width}}  {line}" for name, line in found]
    if keys := _keys(path):
        lines += ["", "main keys (default):"]
        shown = [(f"{k}={v}" if v else k, comment) for k, v, comment in keys]
        width = max(len(key) for key, _ in shown)
        lines += [f"  {key:<{width}}  {comment}" for key, comment in shown]
    groups = [(g, d, [n for n, _ in found] if g == "experiment" and found else o) for g, d, o in _groups(path)]
    if groups:
        lines += ["", "config groups (group=OPTION; default, then the options):"]
        width = max(len(group) for group, _, _ in groups)
        lines += [f"  {group:<{width}}  {default}: {', '.join(options)}" for group, default, options in groups]
    lines += [
        "",
        f"the whole composed config: kpflow-{command} [overrides] --cfg job (--hydra-help: Hydra's own flags)",
    ]
    return "\n".join(lines)


def entry(command: str):
    """The console script of ``command``: :func:`usage` for ``-h``/``--help``, else the command itself."""

    def main():
        if any(arg in HELP_FLAGS for arg in sys.argv[1:]):
            try:
                print(usage(command), flush=True)
            except BrokenPipeError:  # kpflow-train --help | head: the reader left, nothing is wrong
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return None
        return import_module(f"kpflow.cli.{command}").main()

    main.__name__ = main.__qualname__ = command
    return main


train, evaluate, collect, correct, generate, serve, release, teleop, verify, merge = (entry(c) for c in COMMANDS)
