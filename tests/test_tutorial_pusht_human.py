"""docs/tutorials/pusht-human.md runs as written: imports Diffusion Policy's human Push-T dataset, trains a K-CFM and
evaluates it on the standard protocol (the page runner of tests/test_docs.py, in a file of its own so that the
suite's two workers share the long tutorials). Skipped where the dataset is absent."""

from pathlib import Path

import pytest

from tests.test_docs import DOCS, check_page

REPLAY = Path(__file__).resolve().parents[2] / "shared" / "data" / "pusht_cchi_v7_replay.zarr"


@pytest.mark.slow
@pytest.mark.skipif(not REPLAY.is_dir(), reason=f"the human Push-T dataset is not at {REPLAY}")
def test_the_tutorial_runs(tmp_path, monkeypatch):
    monkeypatch.setenv("PUSHT_REPLAY", str(REPLAY))
    monkeypatch.setenv("KPFLOW_DATA_DIR", str(tmp_path / "data"))  # not the clone's data/: the import makes its own
    check_page(DOCS / "tutorials" / "pusht-human.md", tmp_path)
    assert (tmp_path / "data" / "pusht_human.zarr").is_dir()
    table = (tmp_path / "outputs" / "evaluate_short" / "results.md").read_text()
    assert "| kcfm | standard | 50 |" in table
