"""docs/tutorials/own-task.md runs as written: collects, trains, evaluates (alone and transported), releases and serves the reach task (the page runner of tests/test_docs.py, in a file of its own
so that the suite's two workers share the long tutorials)."""

import pytest

from tests.test_docs import DOCS, check_page


@pytest.mark.slow
def test_the_tutorial_runs(tmp_path):
    check_page(DOCS / "tutorials" / "own-task.md", tmp_path)
