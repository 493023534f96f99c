"""The old command-line spellings of the source search read as the new ones (kpflow/cli/spellings.py)."""

import pytest

from kpflow.cli.spellings import new_spelling


def test_the_old_search_group_is_read_as_the_policys_search():
    args, notes = new_spelling(
        ["policy=transport", "source_search.candidates=5", "source_search.weights.agent=16", "seed=1"]
    )
    assert args == ["policy=transport", "++policy.search.candidates=5", "++policy.search.weights.agent=16", "seed=1"]
    assert len(notes) == 2 and "old spelling of ++policy.search.candidates=5" in notes[0]


def test_a_transported_kcfm_gets_its_transports_search():
    args, _ = new_spelling(["policy=transported_kcfm", "source_search.frame=world"])
    assert args == ["policy=transported_kcfm", "++policy.transport.search.frame=world"]


def test_the_old_group_choices_become_the_tasks_search_or_no_stuck_detection():
    args, notes = new_spelling(["source_search=pusht", "source_search=default"])
    assert args == ["++policy.search.stuck_decisions=false"]
    assert "the task's own" in notes[0]
    with pytest.raises(SystemExit, match="the source_search group is gone"):
        new_spelling(["source_search=mine"])


def test_other_arguments_pass_unchanged():
    args = ["policy.search={candidates: 5}", "source_searching=1", "--help"]
    assert new_spelling(args) == (args, [])


def test_a_commands_own_renamed_key():
    args, notes = new_spelling(["goal=fixed", "n_episodes=3"], {"goal": "options.goal"})
    assert args == ["options.goal=fixed", "n_episodes=3"] and "old spelling of options.goal=fixed" in notes[0]
