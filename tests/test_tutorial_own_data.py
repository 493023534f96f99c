"""docs/tutorials/own-data.md runs as written: trains a K-CFM on a LeRobot dataset, checks it offline, releases and serves it (the page runner of tests/test_docs.py, in a file of its own
so that the suite's two workers share the long tutorials)."""

import pytest

from tests.test_docs import DOCS, check_page


@pytest.mark.slow
def test_the_tutorial_runs(tmp_path):
    check_page(DOCS / "tutorials" / "own-data.md", tmp_path)
    # the example is one where the policy learns (issue 66: run verbatim, it used to lose to holding still)
    report = (tmp_path / "outputs" / "offline" / "mine" / "results.md").read_text()
    assert "The K-CFM beats repeating the previous action" in report, report
