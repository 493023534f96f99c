"""Where collected and imported data go (kpflow/utils/data_dir.py): $KPFLOW_DATA_DIR, a clone's data/, else the user
cache; never the folder a command runs in."""

from pathlib import Path

from hydra import compose, initialize_config_module

from kpflow.utils.data_dir import ENV, data_dir

ROOT = Path(__file__).resolve().parents[1]


def test_the_data_folder_and_the_configs_that_read_it(monkeypatch, tmp_path):
    monkeypatch.delenv(ENV, raising=False)
    assert data_dir() == ROOT / "data"  # running from this clone
    monkeypatch.setenv(ENV, str(tmp_path))
    assert data_dir() == tmp_path
    with initialize_config_module("kpflow.conf", version_base="1.3"):
        expert = compose("evaluate", overrides=["data.n_episodes=35"]).data.path
        human = compose("evaluate", overrides=["data=pusht_human"]).data.path
    assert (expert, human) == (str(tmp_path / "pusht_expert_35.zarr"), str(tmp_path / "pusht_human.zarr"))


def test_a_data_folder_that_is_a_file_is_refused_in_one_line(monkeypatch, tmp_path, capsys):
    """Issue 63.8: ``KPFLOW_DATA_DIR`` naming a file gave a raw OS error at the first write."""
    import pytest

    from kpflow.tasks.pusht.replay_import import main

    (tmp_path / "data").write_text("not a folder")
    monkeypatch.setenv(ENV, str(tmp_path / "data"))
    with pytest.raises(
        ValueError,
        match=rf"KPFLOW_DATA_DIR={tmp_path / 'data'} is not a folder \(it is a file\): point KPFLOW_DATA_DIR at a folder",
    ):
        data_dir()
    with pytest.raises(SystemExit) as stop:
        main([str(tmp_path / "replay.zarr")])  # the import's default destination is in the data folder
    err = capsys.readouterr().err
    assert stop.value.code == 1 and err.startswith(f"error: KPFLOW_DATA_DIR={tmp_path / 'data'} is not a folder"), err
    assert len(err.strip().splitlines()) == 2, err
