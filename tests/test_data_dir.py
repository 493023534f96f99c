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
