"""The data-efficiency figure reads real evaluation runs laid out as <policy>/<n_demos>/results.json."""

import pytest

from kpflow.eval.data_efficiency import main, read_points, table
from kpflow.eval.policy_trial import PolicyTrial
from kpflow.eval.reports.pusht import PushTReport
from kpflow.eval.trials import run_trials
from kpflow.tasks.pusht.demonstrator import PushTExpert
from kpflow.tasks.pusht.task import PushTTask, protocol_counts
from tests.helpers import StandStill


def test_points_table_and_figure_from_real_runs(tmp_path):
    for policy, n, make in (("still", 5, StandStill), ("still", 20, StandStill), ("expert", 5, PushTExpert)):
        trial = PolicyTrial(PushTTask(), make(), PushTReport(), policy, max_steps=6)
        run_trials(
            tmp_path / "runs" / policy / str(n), trial, "all", *protocol_counts(2), workers=1, videos=0, progress=False
        )
    points = read_points(tmp_path / "runs")
    assert {(p.policy, p.n_demos) for p in points} == {("still", 5), ("still", 20), ("expert", 5)}
    assert len(points) == 9 and all(p.episodes == 2 and 0 <= p.ci[0] <= p.success <= p.ci[1] <= 1 for p in points)
    assert all(p.success == 0.0 for p in points if p.policy == "still")  # six steps of standing still cover nothing
    text = table(points)
    assert "| still | 20 | 0.0% [" in text and text.count("\n| ") == 4
    assert text.startswith("# Push-T: success against the number of demonstrations\n")  # a page with a title
    out = tmp_path / "fig.png"
    main([str(tmp_path / "runs"), "--out", str(out)])
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.with_suffix(".md").read_text() == text
    (tmp_path / "runs" / "still" / "many").mkdir()
    (tmp_path / "runs" / "still" / "many" / "results.json").write_text("{}")
    with pytest.raises(ValueError, match="number of demonstrations"):
        read_points(tmp_path / "runs")
    with pytest.raises(FileNotFoundError, match="no <policy>/<n_demos>/results.json"):
        read_points(tmp_path / "empty")
