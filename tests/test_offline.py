"""The offline check (kpflow/eval/offline.py): decisions on the held-out episodes only, errors measured against the
recorded actions, and the repeat-the-previous-action baseline exact where it must be."""

import json

import lightning
import matplotlib.pyplot
import numpy as np
import pytest

from kpflow.data.chunks import ChunkDataModule
from kpflow.data.episode_store import EpisodeStore
from kpflow.eval.offline import evaluate_offline
from kpflow.policies.kcfm.model import KCFM


@pytest.fixture
def checkpoint_and_data(tmp_path):
    """Episodes whose action never changes (each its own constant target): the previous action is always right."""
    rng = np.random.default_rng(0)
    with EpisodeStore(tmp_path / "demos.zarr", mode="a") as store:
        for _ in range(10):
            target = rng.uniform(0, 1, 2).astype(np.float32)
            keypoints = np.repeat(np.vstack([target, rng.uniform(0, 1, 2)])[None], 12, axis=0).astype(np.float32)
            store.add_episode({"keypoints": keypoints, "action": np.repeat(target[None], 12, axis=0)})
    data = ChunkDataModule(tmp_path / "demos.zarr", horizon=8, n_obs=2, batch_size=32, val_fraction=0.2)
    lightning.seed_everything(0, verbose=False)
    model = KCFM(**data.model_dims(), horizon=8, n_obs=2, network={"name": "unet", "down_dims": [16, 32]})
    trainer = lightning.Trainer(max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                                enable_model_summary=False, default_root_dir=tmp_path)  # fmt: skip
    model.fit_processor(data.training_chunks())
    trainer.fit(model, datamodule=data)
    trainer.save_checkpoint(tmp_path / "kcfm.ckpt")
    return tmp_path / "kcfm.ckpt", ChunkDataModule(tmp_path / "demos.zarr", horizon=8, n_obs=2, val_fraction=0.2)


def test_the_check_decides_on_held_out_steps_and_scores_the_baseline_exactly(checkpoint_and_data, tmp_path):
    checkpoint, data = checkpoint_and_data
    out = tmp_path / "offline"
    out.mkdir()
    result = evaluate_offline(out, 0, str(checkpoint), data, steps=2, execute=4, every=3, progress=False)
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert {r["episode"] for r in rows} == set(data.val_episodes) and {r["t"] for r in rows} == {0, 3, 6, 9}
    assert result["decisions"] == 4 * len(data.val_episodes) and result["split"] == "held-out"
    assert result["hold_first_action_median"] == 0.0 and result["hold_chunk_median"] == 0.0  # constant actions
    assert result["first_action_median"] > 0 and np.isfinite(result["chunk_p90"])  # an untrained network is not exact
    assert (out / "offline.png").is_file() and "| repeat the previous action | 0 | 0 |" in result["table"]
    assert not result["beats_baseline"] and "**The K-CFM loses to repeating the previous action**" in result["table"]


def test_every_must_be_positive(checkpoint_and_data, tmp_path):
    checkpoint, data = checkpoint_and_data
    with pytest.raises(ValueError, match="every must be >= 1"):
        evaluate_offline(tmp_path, 0, str(checkpoint), data, every=0)


def test_the_figure_names_the_dimensions_and_ends_the_chunks_at_the_episode_end(tmp_path, monkeypatch):
    """Titles from the layout (x, y, z and the gripper of a 10-D arm action, the 6-D rotation left out) and no
    predicted chunk drawn past the episode's last step."""
    from kpflow.eval import plots
    from kpflow.eval.offline import action_names, shown_dims

    layout = {"n_keypoints": 4, "keypoint_dim": 3, "action_dim": 10, "rotation": True}
    names = action_names(10, layout)
    assert names[:3] == ["x position", "y position", "z position"] and names[-1] == "gripper"
    assert shown_dims(names) == [0, 1, 2, 9]
    assert action_names(2, layout=None) == ["action dim 0", "action dim 1"]
    assert action_names(2, {"keypoint_dim": 2}, columns=["dx", "dy"]) == ["dx", "dy"]  # the dataset's own names
    figures = []
    monkeypatch.setattr(plots, "close", figures.append)
    recorded = np.zeros((30, 10))
    path = plots.offline_figure(tmp_path / "offline.png", recorded, [0, 20, 28], [np.ones((8, 10))] * 3, 5,
                                names=names, dims=shown_dims(names))  # fmt: skip
    assert path.is_file()
    (fig,) = figures
    assert [ax.get_title() for ax in fig.axes] == ["x position", "y position", "z position", "gripper"]
    for ax in fig.axes:
        recorded_line, *chunks = ax.get_lines()
        assert len(recorded_line.get_xdata()) == 30 and len(chunks) == 3
        assert max(line.get_xdata()[-1] for line in chunks) == 29  # the episode's last step, not 28 + 7
    matplotlib.pyplot.close(fig)
