"""The Hydra entry points run end to end and write their resolved config beside their results."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_evaluate_frames_writes_config_table_and_plots(tmp_path):
    cmd = [
        sys.executable,
        "evaluate.py",
        "experiment=frames",
        "map=ilwr",
        "logger=csv",
        "seed=3",
        "experiment.n_configs=3",
        "task.n_points=60",
        f"hydra.run.dir={tmp_path}",
    ]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    cfg = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert cfg["seed"] == 3 and cfg["map"]["_target_"] == "kpflow.maps.ILWRMap" and cfg["experiment"]["n_configs"] == 3
    results = json.loads((tmp_path / "results.json").read_text())
    assert len(results["figure2"]["configs"]) == 3
    assert results["figure2"]["mean"]["final_position_error"] < 0.1
    for scene in results["figure1"]["scenes"]:
        assert scene["start_error"] < 1e-2 and scene["final_position_error"] < 1e-2  # frames' origins reached
    assert "| mean |" in (tmp_path / "results.md").read_text()
    for png in ("figure1.png", "figure2.png"):
        assert (tmp_path / png).stat().st_size > 10_000
    assert list((tmp_path / "csv").rglob("metrics.csv")), "CSV logger wrote nothing"


@pytest.mark.slow
def test_same_seed_same_numbers(tmp_path):
    def run(d):
        cmd = [
            sys.executable,
            "evaluate.py",
            "experiment=frames",
            "map=gp",
            "logger=none",
            "experiment.n_configs=2",
            "task.n_points=50",
            f"hydra.run.dir={d}",
        ]
        subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True, timeout=300)
        return json.loads((d / "results.json").read_text())

    assert run(tmp_path / "a") == run(tmp_path / "b")


@pytest.mark.slow
def test_multirun_sweep_writes_one_run_per_map(tmp_path):
    cmd = [
        sys.executable,
        "evaluate.py",
        "-m",
        "experiment=frames",
        "map=affine,ilwr",
        "logger=none",
        "experiment.n_configs=2",
        "task.n_points=40",
        f"hydra.sweep.dir={tmp_path}",
    ]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    targets = sorted(yaml.safe_load((tmp_path / str(k) / "config.yaml").read_text())["map"]["_target_"] for k in (0, 1))
    assert targets == ["kpflow.maps.AffineMap", "kpflow.maps.ILWRMap"]
    assert all((tmp_path / str(k) / "results.json").exists() for k in (0, 1))


@pytest.mark.slow
def test_evaluate_pusht_writes_table_plot_videos_and_config(tmp_path):
    cmd = [
        sys.executable, "evaluate.py", "policy=nearest", "condition=all", "n_configs=2", "workers=2", "logger=csv",
        "data.n_episodes=2", f"data.path={tmp_path / 'demos.zarr'}", "experiment.trial.max_steps=60", f"hydra.run.dir={tmp_path / 'run'}",
    ]  # fmt: skip
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    run = tmp_path / "run"
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    assert (
        cfg["policy"]["_target_"] == "kpflow.policies.factory.nearest"
        and cfg["condition"] == "all"
        and cfg["split"] is None
    )
    results = json.loads((run / "results.json").read_text())
    assert [s["condition"] for s in results["summary"]] == ["in_distribution", "robot_ood", "object_ood"] and len(
        results["trials"]
    ) == 6
    for s in results["summary"]:
        lo, hi = s["ci_085"]
        assert 0.0 <= lo <= s["success_085"] <= hi <= 1.0 and s["latency_ms"] > 0
    assert "| nearest | robot_ood | 2 |" in (run / "results.md").read_text()
    assert (run / "success.png").stat().st_size > 0 and list(run.glob("*.mp4"))


@pytest.mark.slow
def test_pusht_sweep_in_parallel_writes_one_combined_table(tmp_path):
    cmd = [
        sys.executable, "evaluate.py", "-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "policy=nearest,transport",
        "split=in_distribution", "n_configs=2", "workers=1", "logger=none", "data.n_episodes=2", "data.workers=1",
        f"data.path={tmp_path / 'demos.zarr'}", "experiment.trial.max_steps=30", "experiment.videos=0", f"hydra.sweep.dir={tmp_path / 'sweep'}",
    ]  # fmt: skip
    from kpflow.tasks.pusht.collection import collect_pusht

    collect_pusht(tmp_path / "demos.zarr", 2, workers=1, progress=False)  # both jobs then read the same store
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    table = (tmp_path / "sweep" / "table.md").read_text().splitlines()
    assert sum(line.startswith("| policy ") for line in table) == 1  # one header
    assert any(line.startswith("| nearest | in_distribution | 2 |") for line in table)
    assert any(line.startswith("| transport | in_distribution | 2 |") for line in table)


@pytest.mark.slow
def test_correct_cli_grows_a_copy_of_the_demonstrations(tmp_path):
    demos = tmp_path / "demos.zarr"
    cmd = [
        sys.executable, "-m", "kpflow.cli.correct", "policy=nearest", "policy.relative=false", "rounds=2",
        "episodes_per_round=2", "max_steps=80", "stuck_steps=10", "takeover_steps=20", "data.n_episodes=2",
        "data.workers=1", f"data.path={demos}", "eval_configs=2", "eval_max_steps=30", "workers=1",
        f"hydra.run.dir={tmp_path / 'run'}",
    ]  # fmt: skip
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    from kpflow.data.episode_store import EpisodeStore

    run = tmp_path / "run"
    original, grown = EpisodeStore(demos), EpisodeStore(run / "episodes.zarr")
    assert len(original) == 2  # the demonstrations themselves are left alone
    rounds = json.loads((run / "rounds.json").read_text())
    assert rounds["start_steps"] == original.n_steps and [r["round"] for r in rounds["rounds"]] == [0, 1]
    assert grown.n_steps == rounds["rounds"][-1]["dataset_steps"] > original.n_steps  # absolute replays get stuck
    assert [e["episodes"] for e in rounds["evaluations"]] == [2, 2, 2]  # before, after round 0, after round 1
    assert (run / "eval_round1" / "results.json").exists()
    assert "| 1 | 2 |" in (run / "rounds.md").read_text() and (run / "rounds.png").stat().st_size > 0
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    assert cfg["policy"]["_target_"] == "kpflow.policies.factory.nearest" and cfg["rounds"] == 2


def test_an_evaluation_builds_its_task_once(tmp_path):
    """Every ``${task}`` of the experiment and the policy is the one task object (it was built once per mention),
    and the config written keeps the task's config."""
    from hydra import compose, initialize_config_module
    from hydra.core.hydra_config import HydraConfig
    from hydra.utils import instantiate

    from kpflow.cli.evaluate import with_task_built
    from kpflow.tasks.pusht.task import PushTTask

    with initialize_config_module("kpflow.conf", version_base="1.3"):
        cfg = compose("evaluate", return_hydra_config=True, overrides=["policy=kcfm", "checkpoint=release:pusht_standard_fast",
                      "logger=none", f"output_dir={tmp_path}"])  # fmt: skip
    HydraConfig.instance().set_config(cfg)
    built, task = with_task_built(cfg)
    assert isinstance(task, PushTTask) and built.experiment.trial.task is task and built.policy.task is task
    assert cfg.task._target_ == "kpflow.tasks.pusht.task.PushTTask"  # the run's own config is left as it was
    run = instantiate(built.experiment)  # run_trials with its trial, the policy built for the same task
    assert run.keywords["trial"].task is task
