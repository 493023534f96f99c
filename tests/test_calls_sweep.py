"""The calls sweep reads run folders (the checkpoint's own sampling settings when the config leaves them null) into
a table and a figure, and refuses a pattern that matches no finished run."""

import json

import pytest
import yaml

from kpflow.eval.calls_sweep import main, read_run
from kpflow.policies.kcfm.model import KCFM
from kpflow.tasks.pusht.geometry import N_KEYPOINTS


def _run(folder, steps, solver, success, checkpoint="x.ckpt"):
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(
        yaml.safe_dump({"policy": {"checkpoint": str(checkpoint), "steps": steps, "solver": solver}})
    )
    summary = {"condition": "standard", "episodes": 200, "success_085": success + 0.1, "ci_085": [success, success + 0.2],
               "success_095": success, "ci_095": [success - 0.05, success + 0.05], "score": 0.9, "latency_ms": 3.0}  # fmt: skip
    (folder / "results.json").write_text(json.dumps({"summary": [summary]}))


def test_the_sweep_reads_runs_into_a_table_and_a_figure(tmp_path):
    _run(tmp_path / "runs" / "a_euler1", 1, "euler", 0.5)
    _run(tmp_path / "runs" / "a_euler2", 2, "euler", 0.7)
    model = KCFM(
        N_KEYPOINTS,
        horizon=4,
        network={"name": "unet", "down_dims": (8, 16), "time_dim": 8},
        sampler={"steps": 3, "solver": "heun"},
    )
    ckpt = tmp_path / "own.ckpt"
    import torch

    torch.save({"state_dict": model.state_dict(), "hyper_parameters": dict(model.hparams)}, ckpt)
    _run(tmp_path / "runs" / "b_own", None, None, 0.8, ckpt)
    (row,) = read_run("b", tmp_path / "runs" / "b_own")
    assert (row.calls, row.solver, row.success_095) == (3, "heun", 0.8)
    main([f"a={tmp_path}/runs/a_*", f"b={tmp_path}/runs/b_*", "--out", str(tmp_path / "out")])
    lines = (tmp_path / "out" / "sweep.md").read_text().splitlines()
    assert [line.split(" | ")[2] for line in lines[2:]] == ["1", "2", "3"]  # calls ascending within a label
    assert "| a | euler | 2 | standard | 200 | 80.0% [70.0, 90.0] | 70.0% [65.0, 75.0] | 0.900 |" in lines[3]
    assert (tmp_path / "out" / "sweep.png").stat().st_size > 10_000
    with pytest.raises(SystemExit, match="matching finished run folders"):
        main([f"c={tmp_path}/none_*", "--out", str(tmp_path / "out")])


def test_the_sweep_figure_keeps_its_legend_off_the_lines(tmp_path, monkeypatch):
    """The legend sits right of the score panel, outside both axes, so it covers no curve or interval."""
    import matplotlib.pyplot

    from kpflow.eval import calls_sweep

    figures = []
    monkeypatch.setattr(calls_sweep, "close", figures.append)
    for calls, success in ((1, 0.4), (2, 0.6), (4, 0.8)):
        _run(tmp_path / "runs" / f"a_euler{calls}", calls, "euler", success)
    rows = [r for f in sorted((tmp_path / "runs").iterdir()) for r in read_run("a", f)]
    calls_sweep.figure(rows, tmp_path / "sweep.png")
    (fig,) = figures
    fig.canvas.draw()
    success_ax, score_ax = fig.axes
    legend = score_ax.get_legend()
    assert success_ax.get_legend() is None and legend.get_window_extent().x0 > score_ax.get_window_extent().x1
    matplotlib.pyplot.close(fig)
