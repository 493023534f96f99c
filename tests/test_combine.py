"""The sweep-table callback: every job's rows, then the jobs that split one evaluation by trial ranges pooled into
the row one run over all their trials gives (real Push-T episodes through the one trial loop)."""

import pytest
import yaml

from kpflow.eval.combine import combine_tables, results_files
from kpflow.eval.policy_trial import PolicyTrial
from kpflow.eval.reports.pusht import PushTReport
from kpflow.eval.trials import run_trials
from kpflow.tasks.pusht.task import PushTTask
from tests.helpers import StandStill

SPLIT = "in_distribution"


def job(folder, first: int, n: int, seed: int = 0):
    trial = PolicyTrial(PushTTask(), StandStill(), PushTReport(), "still", max_steps=5)
    run_trials(
        folder,
        trial,
        SPLIT,
        n_trials={SPLIT: n},
        first_index={SPLIT: first},
        seed=seed,
        workers=1,
        videos=0,
        progress=False,
    )
    config = {"seed": seed, "policy": "still", "output_dir": str(folder), "n_configs": n,
              "experiment": {"trial": {"report": {"_target_": "kpflow.eval.reports.pusht.PushTReport"}, "max_steps": 5},
                             "first_index": {SPLIT: first}, "n_trials": {SPLIT: n}}}  # fmt: skip
    (folder / "config.yaml").write_text(yaml.safe_dump(config))


def rows(text: str) -> list[list[str]]:
    return [line.split(" | ")[:-1] for line in text.splitlines() if line.startswith("| still")]  # all but latency


def test_shards_of_one_evaluation_pool_into_one_runs_row(tmp_path):
    job(tmp_path / "sweep" / "0", 0, 3)
    job(tmp_path / "sweep" / "1", 3, 2)
    job(tmp_path / "whole", 0, 5)
    text = combine_tables(tmp_path / "sweep").read_text()
    per_job, pooled = text.split("## Pooled")
    assert len(rows(per_job)) == 2 and "jobs 0, 1" in pooled and "5 trials" in pooled
    assert rows(pooled) == rows((tmp_path / "whole" / "results.md").read_text())
    assert rows(pooled)[0][2] == "5"


def test_repeats_and_other_evaluations_are_not_pooled(tmp_path):
    job(tmp_path / "sweep" / "0", 0, 2)
    job(tmp_path / "sweep" / "1", 0, 2)  # the same trials again
    job(tmp_path / "sweep" / "2", 2, 2, seed=1)  # another seed: another evaluation
    text = combine_tables(tmp_path / "sweep").read_text()
    assert "## Pooled" not in text and len(rows(text)) == 3


def _plant_report(folder, report: dict) -> None:
    config = yaml.safe_load((folder / "config.yaml").read_text())
    config["experiment"]["trial"]["report"] = report
    (folder / "config.yaml").write_text(yaml.safe_dump(config))


@pytest.mark.parametrize("report, refused", [
    ({"_target_": "kpflow.eval.reports.pusht.PushTReport", "x": {"_target_": "os.system", "command": "touch {pwned}"}}, r"experiment.trial.report.x._target_ is refused"),
    ({"_target_": "kpflow.eval.reports.pusht.PushTReport", "_args_": ["touch {pwned}"]}, r"experiment.trial.report._args_ is refused"),
    ({"_target_": "os.system", "command": "touch {pwned}"}, r"experiment.trial.report names .os.system., not one of kpflow.s reports"),
    ({"_target_": "kpflow.eval.reports.pusht.os.system", "command": "touch {pwned}"}, r"experiment.trial.report names .kpflow.eval.reports.pusht.os.system., not one of"),
    ({"_target_": "kpflow.eval.reports.pusht.trial_from_record", "record": "touch {pwned}"}, r"experiment.trial.report names .kpflow.eval.reports.pusht.trial_from_record., which is not a report class"),
])  # fmt: skip
def test_a_job_config_naming_code_is_refused_and_nothing_runs(tmp_path, report, refused):
    """Issue 63.1: a target anywhere in the report options a job's config.yaml holds is refused by name, never built."""
    pwned = tmp_path / "pwned"
    job(tmp_path / "sweep" / "0", 0, 3)
    job(tmp_path / "sweep" / "1", 3, 2)
    _plant_report(tmp_path / "sweep" / "1", yaml.safe_load(yaml.safe_dump(report).replace("{pwned}", str(pwned))))
    _plant_report(tmp_path / "sweep" / "0", yaml.safe_load(yaml.safe_dump(report).replace("{pwned}", str(pwned))))
    with pytest.raises(ValueError, match=rf"sweep/0/config.yaml: {refused}"):
        combine_tables(tmp_path / "sweep")
    assert not pwned.exists()


def test_only_the_tables_this_sweep_wrote_are_combined(tmp_path):
    """Issue 63.1: a results.md that was in the sweep folder before the sweep began is not one of its jobs."""
    job(tmp_path / "sweep" / "7", 0, 2, seed=3)  # a former run's table, left in the folder
    before = results_files(tmp_path / "sweep")
    job(tmp_path / "sweep" / "0", 0, 2)
    text = combine_tables(tmp_path / "sweep", before).read_text()
    assert len(rows(text)) == 1
    assert len(rows(combine_tables(tmp_path / "sweep").read_text())) == 2  # without the snapshot: every table
