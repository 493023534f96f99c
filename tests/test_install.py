"""kpflow as a package, not a checkout: its wheel holds the configs, assets and ``py.typed``, installs into a fresh
venv without an editable link and runs its commands (the demo included) from a folder that is not the repository.

The fresh venv takes kpflow from the wheel only; its dependencies are the test environment's, reached through a
``.pth`` line (no download: the suite runs offline). The full resolution (``pip install -c constraints.txt .`` into
an empty venv) is what ``make venv`` and docs/install.md do."""

import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

from tests.helpers import child_env

ROOT = Path(__file__).resolve().parents[1]


def run(args, cwd, timeout=600, **env):
    done = subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env=child_env(OMP_NUM_THREADS="1", WANDB_MODE="offline", MPLBACKEND="Agg", **env))  # fmt: skip
    assert done.returncode == 0, f"{args}: {done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    out = tmp_path_factory.mktemp("wheel")
    run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out), str(ROOT)],
        out,
    )
    (path,) = out.glob("kpflow-*.whl")
    return path


def test_the_wheel_holds_configs_assets_and_types(wheel):
    import tomllib

    import kpflow

    assert (
        wheel.name.startswith(f"kpflow-{kpflow.__version__}-")
        and kpflow.__version__ == tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    )
    names = set(zipfile.ZipFile(wheel).namelist())
    for name in ("kpflow/py.typed", "kpflow/conf/train.yaml", "kpflow/conf/evaluate.yaml", "kpflow/conf/task/pusht.yaml",
                 "kpflow/conf/experiment/kcfm.yaml", "kpflow/conf/hydra/launcher/slurm.yaml", "kpflow/cli/train.py"):  # fmt: skip
        assert name in names, name
    assert any(n.startswith("kpflow/tasks/arm/assets/") and n.endswith(".xml") for n in names)
    entry_points = next(n for n in names if n.endswith("entry_points.txt"))
    scripts = zipfile.ZipFile(wheel).read(entry_points).decode()
    for command in (
        "train",
        "evaluate",
        "collect",
        "correct",
        "generate",
        "merge",
        "serve",
        "release",
        "teleop",
        "verify",
    ):
        assert (
            f"kpflow-{command} = kpflow.cli.usage:{command}" in scripts
        )  # --help from usage.py, the rest kpflow.cli.<command>.main
    assert (
        "kpflow-connect = kpflow.examples.connect:main" in scripts
        and "kpflow-example = kpflow.examples:main" in scripts
    )
    for name in ("kpflow/examples/connect.py", "kpflow/examples/templates/reach_task/reach/task.py",
                 "kpflow/examples/templates/reach_task/conf/task/reach.yaml", "kpflow/examples/templates/reach_task/drive.py"):  # fmt: skip
        assert name in names, name  # what the guides use, without a clone


@pytest.mark.slow
def test_a_fresh_venv_runs_the_commands_and_the_demo_from_another_folder(wheel, tmp_path):
    venv = tmp_path / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", str(venv)], tmp_path)
    site = Path(
        run(
            [str(venv / "bin" / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path
        ).stdout.strip()
    )
    (site / "test_environment.pth").write_text(
        sysconfig.get_paths()["purelib"] + "\n"
    )  # the dependencies, after the venv's own
    run(
        [
            sys.executable,
            "-m",
            "pip",
            "--python",
            str(venv / "bin" / "python"),
            "install",
            "-q",
            "--no-deps",
            "--no-index",
            str(wheel),
        ],
        tmp_path,
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    where = run(
        [str(venv / "bin" / "python"), "-c", "import kpflow, kpflow.conf; print(kpflow.__file__)"], elsewhere
    ).stdout
    assert where.startswith(str(site)), where  # the installed copy, not the checkout
    assert (
        "experiments (experiment=NAME):\n  frames "
        in run([str(venv / "bin" / "kpflow-evaluate"), "--help"], elsewhere).stdout
    )
    demo = run([str(venv / "bin" / "kpflow-evaluate"), "experiment=pusht_demo", "n_configs=2", "workers=1", "logger=none",
                "experiment.videos=0", "hydra.run.dir=demo"], elsewhere)  # fmt: skip
    assert all(
        f"| transport | {split} | 2 |" in demo.stdout for split in ("in_distribution", "robot_ood", "object_ood")
    ), demo.stdout[-2000:]
    assert (elsewhere / "demo" / "results.md").is_file() and (elsewhere / "demo" / "config.yaml").is_file()
    assert not (ROOT / "demo").exists()
