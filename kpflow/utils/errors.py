"""How every command reports a failure: one short line naming the problem, the traceback only on request.

kpflow's errors say what is wrong and where (the file, the field, the config key), so the 30-70 lines of traceback
above such a message bury it. :func:`command` wraps an entry point: an exception ends the process with exit code 1
and ``error: <message>`` on stderr, followed by one line saying how to see the traceback. With the environment
variable ``KPFLOW_TRACEBACK=1`` (or Hydra's own ``HYDRA_FULL_ERROR=1``) the exception propagates unchanged, traceback
and all. ``KeyboardInterrupt`` and ``SystemExit`` are never caught.

Hydra reads a config group's YAML only when it composes it, and a file that does not parse then ends the run with
Hydra's own traceback; :func:`config_dir_checked` reads every YAML under ``--config-dir`` first and refuses a broken
one in the same single line, naming the file, line and column.

Hydra's ``instantiate`` wraps a constructor's error in an ``InstantiationException`` whose text repeats the target
and the config key; the message shown is the constructor's own (the innermost cause), prefixed with the config key.
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path
from typing import Callable, TypeVar

TRACEBACK_ENV = "KPFLOW_TRACEBACK"
F = TypeVar("F", bound=Callable)


def full_traceback_wanted() -> bool:
    """True when ``KPFLOW_TRACEBACK`` or ``HYDRA_FULL_ERROR`` is set to anything but ``0``/empty."""
    return any(os.environ.get(name, "0") not in ("", "0") for name in (TRACEBACK_ENV, "HYDRA_FULL_ERROR"))


def describe(error: BaseException) -> str:
    """The one-line account of ``error``: its own message, or for a Hydra instantiation error the innermost cause's,
    prefixed by the config key it came from."""
    from hydra.errors import InstantiationException

    key = None
    while isinstance(error, InstantiationException) and error.__cause__ is not None:
        text = str(error)
        if "full_key: " in text:
            key = text.rsplit("full_key: ", 1)[1].strip() or key
        error = error.__cause__
    from omegaconf.errors import InterpolationToMissingValueError, MissingMandatoryValue

    # a ??? left in the config, or a key pointing at one (policy.checkpoint: ${checkpoint}): name it and how to give it
    if isinstance(error, (MissingMandatoryValue, InterpolationToMissingValueError)):
        pointed = isinstance(
            error, InterpolationToMissingValueError
        )  # its full_key is the pointing key, not the missing one
        missing = (not pointed and getattr(error, "full_key", None)) or str(error).splitlines()[0].split(":")[
            -1
        ].strip()
        return f"config key {missing} is required and not given: add {missing}=<value> to the command"
    message = str(error).strip() or type(error).__name__
    if isinstance(error, (KeyError,)) and message.startswith(("'", '"')):
        message = message[1:-1]
    what = "" if isinstance(error, (ValueError, FileNotFoundError, FileExistsError)) else f"{type(error).__name__}: "
    return (f"{key}: " if key else "") + what + message


def command(main: F) -> F:
    """Wrap an entry point (a Hydra task function or an argparse ``main``) so that a failure prints
    :func:`describe`'s line and exits with 1 (module docstring)."""

    @functools.wraps(main)
    def wrapper(*args, **kwargs):
        if full_traceback_wanted():
            return main(*args, **kwargs)
        try:
            return main(*args, **kwargs)
        except Exception as error:  # noqa: BLE001 -- every failure gets the one-line account
            print(f"error: {describe(error)}", file=sys.stderr, flush=True)
            print(f"(set {TRACEBACK_ENV}=1 for the full traceback)", file=sys.stderr, flush=True)
            sys.exit(1)

    return wrapper  # type: ignore[return-value]


def config_dirs(argv: list[str]) -> list[str]:
    """The folders ``--config-dir DIR``, ``--config-dir=DIR`` and ``-cd DIR`` name in a command line."""
    out = []
    for i, arg in enumerate(argv):
        if arg in ("--config-dir", "-cd") and i + 1 < len(argv):
            out.append(argv[i + 1])
        elif arg.startswith("--config-dir="):
            out.append(arg.split("=", 1)[1])
    return out


def broken_yaml(folder: str) -> str | None:
    """The first YAML file under ``folder`` that does not parse, as one line (file, line, column, problem), or None."""
    import yaml

    for path in sorted(p for p in Path(folder).rglob("*") if p.suffix in (".yaml", ".yml") and p.is_file()):
        try:
            yaml.safe_load(path.read_text())
        except yaml.YAMLError as e:
            mark = getattr(e, "problem_mark", None)
            where = f", line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
            return f"{path}{where}: not valid YAML ({getattr(e, 'problem', None) or e})"
        except (OSError, UnicodeDecodeError) as e:
            return f"{path}: unreadable ({e})"
    return None


def config_dir_checked(main: F) -> F:
    """Wrap a Hydra entry point (outside ``hydra.main``) so that a broken YAML under ``--config-dir`` is refused in
    one line before Hydra composes anything (module docstring)."""

    @functools.wraps(main)
    def wrapper(*args, **kwargs):
        if not full_traceback_wanted():
            for folder in config_dirs(sys.argv[1:]):
                if (problem := broken_yaml(folder)) is not None:
                    print(f"error: {problem}", file=sys.stderr, flush=True)
                    print(f"(set {TRACEBACK_ENV}=1 for the full traceback)", file=sys.stderr, flush=True)
                    sys.exit(1)
        return main(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
