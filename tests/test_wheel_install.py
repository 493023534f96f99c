"""A newcomer's afternoon without a clone: kpflow installed from its wheel into a fresh venv, and the README's and
the own-task tutorial's commands run from a folder outside the repository, without PYTHONPATH.

The wheel is built offline from a copy of the package's files (``pip wheel --no-deps --no-build-isolation
--no-index``; the test skips, saying why, where that cannot be done). The fresh venv takes kpflow from the wheel only
(checked: ``kpflow.__file__`` lies in the venv); its dependencies are the test environment's, reached through a
``.pth`` line, so nothing is downloaded. HOME is a fresh folder, so the user cache of released checkpoints is empty.
Run, in order: the README's quickstart snippet, ``kpflow-train --help``, ``kpflow-example``, the README's deploy
snippet with a released checkpoint by name (``release:NAME``, from the wheel's own kpflow/release/) and the error for
a name it does not release, then the own-task tutorial's commands as written (``kpflow-example reach_task my_project``, collect,
train, evaluate alone and transported, release, serve, drive), shortened to 5 evaluation scenes per condition and
run on a free port, and README steps 4-5 (``kpflow-serve`` and ``kpflow-connect``) on the policy it trained. About
2 minutes on 2 cores."""

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.helpers import child_env
from tests.test_docs import code_blocks

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
#: what the tutorial's commands are shortened by: (text in docs/tutorials/own-task.md, replacement, times it occurs)
SHORTEN = [("experiment.n_trials=20", "experiment.n_trials=5", 2)]


def run(args: list[str], cwd: Path, env: dict, timeout: float = 600, code: int = 0) -> subprocess.CompletedProcess:
    """Run ``args`` in ``cwd`` in a session of its own (a server it started in the background ends with it), and
    check that it exits with ``code``."""
    proc = subprocess.Popen(
        args, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"{args} ran past {timeout} s:\n{out[-3000:]}\n{err[-3000:]}")
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    done = subprocess.CompletedProcess(args, proc.returncode, out, err)
    assert done.returncode == code, f"{args} exited {done.returncode}, not {code}:\n{out[-3000:]}\n{err[-3000:]}"
    return done


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def venv(tmp_path_factory) -> Path:
    """A fresh venv with kpflow installed from a wheel of this checkout (its dependencies: the test environment's)."""
    tmp = tmp_path_factory.mktemp("wheel_install")
    src = (
        tmp / "src"
    )  # the files a wheel is built from, so that no build/ or egg-info of the checkout is reused or written
    shutil.copytree(ROOT / "kpflow", src / "kpflow", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, src / name)
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q", "-w", str(tmp / "dist"), str(src)],
                           cwd=tmp, capture_output=True, text=True, timeout=600)  # fmt: skip
    wheels = list((tmp / "dist").glob("kpflow-*.whl"))
    if built.returncode or len(wheels) != 1:
        pytest.skip(
            f"the wheel cannot be built offline here (pip wheel exited {built.returncode}): {built.stderr.strip()[-500:]}"
        )
    env = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env)], check=True, timeout=300)
    site = Path(subprocess.run([str(env / "bin" / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())  # fmt: skip
    (site / "test_environment.pth").write_text(
        sysconfig.get_paths()["purelib"] + "\n"
    )  # the dependencies, after the venv's own
    subprocess.run([sys.executable, "-m", "pip", "--python", str(env / "bin" / "python"), "install", "-q", "--no-deps", "--no-index", str(wheels[0])],
                   check=True, capture_output=True, timeout=300)  # fmt: skip
    return env


@pytest.fixture(scope="module")
def newcomer(venv, tmp_path_factory) -> tuple[Path, dict]:
    """A folder outside the repository and the environment a newcomer's shell has there: the venv's commands first on
    PATH, no PYTHONPATH, a fresh HOME (an empty cache of released checkpoints), no KPFLOW_RELEASE_DIR."""
    folder = tmp_path_factory.mktemp("newcomer")
    (folder / "home").mkdir()
    env = child_env(PATH=f"{venv / 'bin'}{os.pathsep}{os.environ['PATH']}", HOME=str(folder / "home"), OMP_NUM_THREADS="1",
                    WANDB_MODE="offline", MPLBACKEND="Agg")  # fmt: skip
    for name in ("PYTHONPATH", "KPFLOW_RELEASE_DIR", "XDG_CACHE_HOME", "VIRTUAL_ENV"):
        env.pop(name, None)
    assert not folder.resolve().is_relative_to(ROOT)
    return folder, env


def python_block(page: Path, containing: str) -> str:
    return next(code for lang, code, _ in code_blocks(page.read_text()) if lang == "python" and containing in code)


def test_kpflow_comes_from_the_wheel_with_what_the_guides_use(venv, newcomer):
    folder, env = newcomer
    where = run(
        ["python", "-c", "import kpflow, kpflow.examples; print(kpflow.__file__); print(kpflow.examples.TEMPLATES)"],
        folder,
        env,
    ).stdout.split()
    assert all(Path(p).is_relative_to(venv) for p in where), where  # the wheel's copy, not the checkout
    assert Path(where[1], "reach_task", "conf", "task", "reach.yaml").is_file()
    assert "experiments (experiment=NAME):" in run(["kpflow-train", "--help"], folder, env).stdout
    assert re.search(r"^  reach_task +A planar reaching task", run(["kpflow-example"], folder, env).stdout, re.M)
    assert "--uri" in run(["python", "-m", "kpflow.examples.connect", "--help"], folder, env).stdout


def test_the_readme_snippets_and_a_release_by_name(newcomer):
    folder, env = newcomer
    readme = ROOT / "README.md"
    (folder / "quickstart.py").write_text(python_block(readme, "ILWRMap().fit"))
    assert "tensor(" in run(["python", "quickstart.py"], folder, env).stdout
    (folder / "deploy.py").write_text(python_block(readme, "release:"))
    shown = run(["python", "deploy.py"], folder, env).stdout  # the wheel carries the releases: no clone, no download
    assert (
        "kcfm {'steps': 20, 'reach': 60.0, 'turn_deg': 60.0} 25 keypoints in" in shown
    )  # the release as its row measured it
    # a name this version does not release: one line says where it looked and what is released
    err = run(["kpflow-serve", "checkpoint=release:pusht_standard_faster", "port=0"], folder, env, code=1).stderr
    cache = Path(env["HOME"], ".cache", "kpflow", "release")
    assert err.startswith(
        "error: no released file pusht_standard_faster.ckpt: looked in $KPFLOW_RELEASE_DIR (not set); "
    ), err
    assert f"(the package's releases); {cache} (the user cache, missing); released there: " in err
    assert "pusht_standard_fast," in err and "Traceback" not in err and "<owner>" not in err


def test_the_own_task_tutorial_runs_from_a_copied_template(newcomer):
    folder, env = newcomer
    port, connect_port = free_port(), free_port()
    blocks = [
        code
        for lang, code, _ in code_blocks((ROOT / "docs" / "tutorials" / "own-task.md").read_text())
        if lang == "bash"
    ]
    script = "\n".join(blocks)
    for text, shorter, times in [*SHORTEN, ("8765", str(port), 2)]:
        assert script.count(text) == times, (
            f"docs/tutorials/own-task.md changed: {text!r} occurs {script.count(text)} times, not {times}"
        )
        blocks = [block.replace(text, shorter) for block in blocks]
    assert blocks[0].startswith("kpflow-example reach_task my_project")
    outputs = [
        run(["bash", "-euo", "pipefail", "-c", block], folder, env).stdout for block in blocks
    ]  # each from the folder, as the page runs
    project = folder / "my_project"
    assert "reach: kcfm in closed loop" in outputs[1] and "| wide | transported_kcfm | 5 |" in outputs[2]
    assert re.search(r"[1-5]/5 episodes reached the target through ws://127\.0\.0\.1:\d+", outputs[3]), outputs[3]
    assert (project / "release" / "reach.source_index.npz").is_file()
    # README steps 4-5 on the policy just released: serve it, and a client asks it for an action chunk
    served = run(["bash", "-euo", "pipefail", "-c", f"kpflow-serve checkpoint=release/reach.ckpt port={connect_port} &\n"
                  f"trap 'kill $!' EXIT\nkpflow-connect --uri ws://127.0.0.1:{connect_port}"], project, env).stdout  # fmt: skip
    assert "server: kcfm, observes" in served and re.search(
        r"action chunk \[8, 2\] in [\d.]+ ms on the server", served
    ), served
    assert not (ROOT / "my_project").exists()
