"""The one trial loop (kpflow/eval/trials.py) with Push-T episodes: the grid, per-condition counts, showcase videos,
the summary rows, and the errors that name a bad grid."""

import json

import pytest

from kpflow.eval.demo_transport_trial import DemoTransportTrial
from kpflow.eval.policy_trial import PolicyTrial
from kpflow.eval.reports.packing import PackingReport
from kpflow.eval.reports.pusht import PushTReport
from kpflow.eval.trials import cell_summary, run_trials
from kpflow.maps import GPMap
from kpflow.tasks.packing.task import PackingTask
from kpflow.tasks.pusht.demonstrator import PushTExpert
from kpflow.tasks.pusht.task import FIRST_CONFIG, PushTTask, protocol_counts
from tests.helpers import StandStill


def test_episode_grid_counts_rows_and_a_filmed_failure(tmp_path):
    n_trials, first_index = protocol_counts(2)
    n_trials["robot_ood"] = 3  # one number per condition
    trial = PolicyTrial(PushTTask(), StandStill(), PushTReport(), "still", max_steps=5)
    results = run_trials(
        tmp_path, trial, ["in_distribution", "robot_ood"], n_trials, first_index, workers=2, videos=1, progress=False
    )
    assert [(t["condition"], t["index"]) for t in results["trials"]] == [
        ("in_distribution", FIRST_CONFIG), ("in_distribution", FIRST_CONFIG + 1),
        ("robot_ood", FIRST_CONFIG), ("robot_ood", FIRST_CONFIG + 1), ("robot_ood", FIRST_CONFIG + 2),
    ]  # fmt: skip
    assert all(
        t["policy"] == "still" and t["steps"] == 5 and not t["success"] and t["failure"] == "time limit"
        for t in results["trials"]
    )
    row = cell_summary(results, "robot_ood")
    assert row["episodes"] == 3 and row["success_085"] == 0.0 and row["policy"] == "still"
    assert results["metrics"]["robot_ood/still/success_095"] == 0.0
    # the showcase: no success to film, the first failure of each split filmed, re-run to the same episode
    assert [p.rsplit("/", 1)[1] for p in results["videos"]] == [
        f"in_distribution_still_{FIRST_CONFIG}_time_limit.mp4",
        f"robot_ood_still_{FIRST_CONFIG}_time_limit.mp4",
    ]
    on_disk = json.loads((tmp_path / "results.json").read_text())
    assert on_disk["task"] == "pusht" and on_disk["policy"] == "still" and on_disk["figures"] == ["success.png"]
    assert "| still | robot_ood | 3 | 0.0% [" in (tmp_path / "results.md").read_text()


def test_the_expert_succeeds_and_its_success_is_filmed(tmp_path):
    trial = PolicyTrial(PushTTask(), PushTExpert("standard"), PushTReport(), "expert", max_steps=600)
    results = run_trials(tmp_path, trial, "in_distribution", 1, FIRST_CONFIG, workers=1, videos=1, progress=False)
    (episode,) = results["trials"]
    assert (
        episode["success"]
        and episode["failure"] is None
        and episode["success_085"]
        and episode["steps_085"] <= episode["steps_095"]
    )
    assert results["videos"][0].endswith(f"in_distribution_expert_{FIRST_CONFIG}_success.mp4")


def test_bad_grids_are_named():
    trial = PolicyTrial(PushTTask(), StandStill(), PushTReport())
    with pytest.raises(ValueError, match="unknown condition"):
        run_trials("unused", trial, ["moved"])
    with pytest.raises(ValueError, match="n_trials names no value for condition 'object_ood'"):
        run_trials("unused", trial, "object_ood", {"in_distribution": 2})
    with pytest.raises(ValueError, match="n_trials and workers must be >= 1"):
        run_trials("unused", trial, "all", 0)
    with pytest.raises(ValueError, match="max_steps must be >= 1"):
        PolicyTrial(PushTTask(), StandStill(), PushTReport(), max_steps=0)
    with pytest.raises(KeyError, match="0 summary rows"):
        cell_summary({"summary": [{"condition": "robot_ood"}]}, "in_distribution")


def test_demo_transport_trial_needs_a_keypoint_source_and_a_map():
    task = PackingTask()
    assert DemoTransportTrial(task, PackingReport(), {"gp": GPMap}).variants() == [{"map": "gp"}]
    with pytest.raises(ValueError, match="at least one keypoint source"):
        DemoTransportTrial(task, PackingReport(), {})
    with pytest.raises(ValueError, match="reserved"):
        DemoTransportTrial(task, PackingReport(), {"gp": GPMap}, backbones={"oracle": object()})


def test_the_success_figure_keeps_its_legends_off_the_bars(tmp_path, monkeypatch):
    """success.png's legends sit under the axes (they cover no bar) and its tick labels are readable."""
    from types import SimpleNamespace

    import matplotlib.pyplot

    from kpflow.core.task import TrialResult
    from kpflow.eval import plots

    figures = []
    monkeypatch.setattr(plots, "close", figures.append)
    scores = lambda c: {"success_085": c >= 0.85, "steps_085": 90, "steps_095": 120, "final_coverage": c,  # noqa: E731
                        "max_coverage": c, "latency_ms": 1.0}  # fmt: skip
    trials = [TrialResult(split, i, {}, {}, c >= 0.95, None, scores(c))
              for split in ("in_distribution", "robot_ood") for i, c in enumerate((0.2, 0.9, 0.97, 1.0))]  # fmt: skip
    assert PushTReport().figures(tmp_path, SimpleNamespace(policy_name="p"), trials, []) == ["success.png"]
    (fig,) = figures
    fig.canvas.draw()
    for ax in fig.axes:
        legend = ax.get_legend().get_window_extent()
        assert legend.y1 < ax.get_window_extent().y0  # below the axes
        assert min(label.get_fontsize() for label in ax.get_xticklabels() + ax.get_yticklabels()) >= 9
    matplotlib.pyplot.close(fig)
