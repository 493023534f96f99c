"""docs/tutorials/mimicgen-benchmark.md runs as written: generates in MimicGen's Stack D1, trains a K-CFM on the
generated episodes and evaluates it alone and transported (the page runner of tests/test_docs.py, in a file of its
own so that the suite's two workers share the long tutorials)."""

import pytest

from tests.test_docs import DOCS, check_page


@pytest.mark.slow
def test_the_tutorial_runs(tmp_path):
    check_page(DOCS / "tutorials" / "mimicgen-benchmark.md", tmp_path)
