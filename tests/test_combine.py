"""The sweep-table callback: every job's rows, then the jobs that split one evaluation by trial ranges pooled into
the row one run over all their trials gives (real Push-T episodes through the one trial loop)."""

import yaml

from kpflow.eval.combine import combine_tables
from kpflow.eval.policy_trial import PolicyTrial
from kpflow.eval.reports.pusht import PushTReport
from kpflow.eval.trials import run_trials
from kpflow.tasks.pusht.task import PushTTask
from tests.helpers import StandStill

SPLIT = "in_distribution"


def job(folder, first: int, n: int, seed: int = 0):
    trial = PolicyTrial(PushTTask(), StandStill(), PushTReport(), "still", max_steps=5)
    run_trials(folder, trial, SPLIT, n_trials={SPLIT: n}, first_index={SPLIT: first}, seed=seed, workers=1, videos=0, progress=False)
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
