"""How every command reports a failure: one short line naming the problem, the traceback only on request.

kpflow's errors say what is wrong and where (the file, the field, the config key), so the 30-70 lines of traceback
above such a message bury it. :func:`command` wraps an entry point: an exception ends the process with exit code 1
and ``error: <message>`` on stderr, followed by one line saying how to see the traceback. With the environment
variable ``KPFLOW_TRACEBACK=1`` (or Hydra's own ``HYDRA_FULL_ERROR=1``) the exception propagates unchanged, traceback
and all. ``KeyboardInterrupt`` and ``SystemExit`` are never caught.

Hydra's ``instantiate`` wraps a constructor's error in an ``InstantiationException`` whose text repeats the target
and the config key; the message shown is the constructor's own (the innermost cause), prefixed with the config key.
"""

from __future__ import annotations

import functools
import os
import sys
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
