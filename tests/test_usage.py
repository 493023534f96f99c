"""kpflow-<command> --help (kpflow/cli/usage.py): a few lines from the config files as they are, without importing
torch or Hydra; anything else runs the command."""

import subprocess
import sys
from pathlib import Path

import pytest

from kpflow.cli.usage import COMMANDS, CONF, experiments, usage

ROOT = Path(__file__).resolve().parents[1]


def test_every_experiment_is_listed_by_exactly_one_command_with_its_first_sentence():
    train, evaluate = dict(experiments("train")), dict(experiments("evaluate"))
    on_disk = {p.stem for p in (CONF / "experiment").glob("*.yaml")}
    assert set(train) | set(evaluate) == on_disk and not set(train) & set(evaluate)
    assert {"kcfm", "pusht_kcfm", "suite_kcfm"} <= set(train) and {"pusht", "offline", "suite_policy"} <= set(evaluate)
    assert train["kcfm"].startswith("A K-CFM on your own demonstrations")
    for command in COMMANDS:
        text = usage(command)
        assert text.startswith(f"kpflow-{command}: ") and f"kpflow-{command} [overrides] --cfg job" in text
    assert "checkpoint=???" in usage("serve") and "seed=0" in usage("train") and "experiment=NAME" in usage("evaluate")
    # issue 66: the help names what exists where kpflow is installed, not a path of the repository
    train_help = usage("train")
    assert train_help.startswith(f"kpflow-train: key=value overrides of {CONF / 'train.yaml'} (Hydra)")
    assert (
        "docs/reference/cli.md" not in train_help
        and "  model       kcfm: kcfm, learned_map, neural_field" in train_help
    )
    assert "  experiment  pusht_kcfm: frames_field, frames_map, kcfm, pusht_kcfm," in train_help  # train's own only
    with pytest.raises(ValueError, match="no command 'nope'; the commands are train, evaluate"):
        usage("nope")


@pytest.mark.parametrize("command", ["train", "evaluate"])
def test_help_imports_neither_torch_nor_hydra(command):
    code = (f"import sys; sys.argv = ['kpflow-{command}', '--help']; from kpflow.cli.usage import {command}; {command}(); "
            "assert 'torch' not in sys.modules and 'hydra' not in sys.modules, 'imported torch or hydra'")  # fmt: skip
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout == usage(command) + "\n"
