"""What ``kpflow-serve`` and ``kpflow-release`` say when they cannot run (issue 40): exit code 1
and at most 3 lines on stderr naming the problem (the host, the port, the file, the config key), the traceback only
with KPFLOW_TRACEBACK=1. A host that does not resolve and a port already taken are refused before the model is
loaded. The real commands, run in this process (their error paths need no fresh interpreter; the traceback switch,
read at start-up, in a subprocess), a real socket holding the port."""

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import run_command

ROOT = Path(__file__).resolve().parents[1]
RELEASED = ROOT / "release" / "pusht_standard_kcfm_human.ckpt"
LOADED = "sha256"  # what serve logs once the model is loaded


def run(*args: str, traceback: bool = False) -> subprocess.CompletedProcess:
    """The command in a fresh process (what a user's shell runs): for the traceback switch, read at start-up."""
    env = {k: v for k, v in os.environ.items() if k not in ("KPFLOW_TRACEBACK", "HYDRA_FULL_ERROR")}
    if traceback:
        env["KPFLOW_TRACEBACK"] = "1"
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=180)


def refused(*args: str) -> subprocess.CompletedProcess:
    """The command run in this process (tests.helpers.run_command): the error paths need no fresh interpreter."""
    return run_command(*args)


def short_failure(done: subprocess.CompletedProcess, *names: str) -> None:
    """Exit code 1, at most 3 lines on stderr, the first ``error: ...`` naming every one of ``names``."""
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and 1 <= len(lines) <= 3, done.stderr
    assert lines[0].startswith("error: ") and all(name in lines[0] for name in names), lines[0]


def test_a_host_that_does_not_resolve_is_refused_before_loading():
    done = refused("kpflow.cli.serve", f"checkpoint={RELEASED}", "host=999.1.1.1", "port=8123")
    short_failure(done, "999.1.1.1", "8123", "does not resolve")
    assert LOADED not in done.stdout  # refused before the model was loaded


def test_kpflow_traceback_shows_the_traceback():
    loud = run("kpflow.cli.serve", f"checkpoint={RELEASED}", "host=999.1.1.1", "port=8123", traceback=True)
    assert loud.returncode == 1 and "Traceback (most recent call last)" in loud.stderr
    assert "ValueError: cannot serve on 999.1.1.1:8123" in loud.stderr


def test_a_port_in_use_is_refused_before_loading():
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        done = refused("kpflow.cli.serve", f"checkpoint={RELEASED}", "host=127.0.0.1", f"port={port}")
    short_failure(done, "127.0.0.1", str(port), "in use")
    assert LOADED not in done.stdout


def test_a_corrupt_checkpoint_is_one_line_for_serve(tmp_path):
    bad = tmp_path / "corrupt.ckpt"
    bad.write_bytes(b"not a checkpoint at all")
    short_failure(
        refused("kpflow.cli.serve", f"checkpoint={bad}", "port=0"),
        str(bad),
        "is not a readable checkpoint (not a torch file",
    )


@pytest.mark.parametrize(
    "content, why",
    [(b"not a checkpoint at all", "not a torch file"), (b"", "the file is empty")],
    ids=["garbage", "empty"],
)
def test_a_corrupt_checkpoint_is_one_line_for_release(tmp_path, content, why):
    bad = tmp_path / "corrupt.ckpt"
    bad.write_bytes(content)
    short_failure(
        refused("kpflow.cli.release", f"src={bad}", f"dst={tmp_path / 'out.ckpt'}"),
        str(bad),
        "is not a readable checkpoint",
        why,
    )
    assert not (tmp_path / "out.ckpt").exists()


@pytest.mark.parametrize(
    "override, message",
    [
        ("max_message_mb=inf", "config key max_message_mb must be a finite number in 0.001..1024; got inf"),
        ("max_message_mb=0", "config key max_message_mb must be a finite number in 0.001..1024; got 0"),
        ("port=70000", "config key port must be an integer in 0..65535; got 70000"),
        ("input_margin=-1", "config key input_margin must be a finite number >= 0 or null; got -1"),
    ],
)
def test_bad_config_keys_are_named(override, message):
    short_failure(refused("kpflow.cli.serve", f"checkpoint={RELEASED}", override), message)
