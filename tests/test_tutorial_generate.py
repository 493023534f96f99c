"""docs/tutorials/generate.md runs as written: generates robosuite demonstrations, in one run and in shards merged (the page runner of tests/test_docs.py, in a file of its own
so that the suite's two workers share the long tutorials)."""

import pytest

from tests.test_docs import DOCS, check_page


@pytest.mark.slow
def test_the_tutorial_runs(tmp_path):
    check_page(DOCS / "tutorials" / "generate.md", tmp_path)
