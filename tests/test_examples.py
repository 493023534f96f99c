"""The examples installed with kpflow (kpflow/examples/): ``kpflow-example`` lists its templates, copies one into a
new or empty folder and refuses to overwrite anything; ``kpflow-connect`` fails in one line when no server answers.
(tests/test_docs.py runs the scripts and the pages that use them; tests/test_wheel_install.py, the installed wheel.)"""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from kpflow.examples import TEMPLATES, copy_template, main, templates


def test_the_templates_are_listed_with_what_they_are(capsys):
    assert list(templates()) == ["reach_task"] and "reaching task" in templates()["reach_task"]
    main([])
    out = capsys.readouterr().out
    assert "kpflow-example NAME DIR" in out and "reach_task" in out and "``" not in out


def test_a_template_is_copied_whole_into_a_new_or_empty_folder(tmp_path, capsys):
    main(["reach_task", str(tmp_path / "my_task")])
    copied = sorted(str(p.relative_to(tmp_path / "my_task")) for p in (tmp_path / "my_task").rglob("*") if p.is_file())
    assert copied == ["conf/task/reach.yaml", "drive.py", "reach/__init__.py", "reach/task.py"]
    assert (tmp_path / "my_task" / "reach" / "task.py").read_text() == (
        TEMPLATES / "reach_task" / "reach" / "task.py"
    ).read_text()
    assert f"copied the reach_task template into {tmp_path / 'my_task'}" in capsys.readouterr().out
    (tmp_path / "empty").mkdir()
    assert (copy_template("reach_task", tmp_path / "empty") / "drive.py").is_file()


def test_nothing_is_overwritten_and_each_refusal_says_what_to_do(tmp_path, capsys):
    target = copy_template("reach_task", tmp_path / "my_task")
    (target / "drive.py").write_text("# mine\n")
    with pytest.raises(SystemExit) as stop:
        main(["reach_task", str(target)])
    assert stop.value.code == 1 and (target / "drive.py").read_text() == "# mine\n"
    assert f"error: {target} is not empty, so nothing was copied: name a new or empty folder" in capsys.readouterr().err
    with pytest.raises(ValueError, match="is a file: name a new or empty folder you can write to"):
        copy_template("reach_task", target / "drive.py")
    with pytest.raises(ValueError, match=r"no template 'reach': kpflow-example copies one of reach_task"):
        copy_template("reach", tmp_path / "other")
    assert not (tmp_path / "other").exists()
    with pytest.raises(SystemExit) as stop:
        main(["reach_task"])
    assert stop.value.code == 2 and "name the folder to copy 'reach_task' into" in capsys.readouterr().err


def _read_only_folder(tmp_path) -> Path:
    """A folder this process cannot write into: mode 0555, or, for root (whom modes do not stop), sysfs."""
    folder = tmp_path / "read_only"
    folder.mkdir(mode=0o555)
    if os.access(folder, os.W_OK):
        if not Path("/sys/kernel").is_dir():
            pytest.skip("no folder this process cannot write into (root without sysfs)")
        return Path("/sys")
    return folder


def test_a_dangling_link_or_read_only_folder_is_refused_in_one_line(tmp_path, capsys):
    """Issue 63.8: these gave raw OS errors."""
    (tmp_path / "link").symlink_to(tmp_path / "gone")
    with pytest.raises(SystemExit) as stop:
        main(["reach_task", str(tmp_path / "link")])
    err = capsys.readouterr().err
    assert stop.value.code == 1 and err.strip().splitlines()[1:] == [
        "(set KPFLOW_TRACEBACK=1 for the full traceback)"
    ], err
    assert (
        f"error: {tmp_path / 'link'} is a symbolic link to {tmp_path / 'gone'}, which does not exist: name a new or empty folder"
        in err
    )
    dest = _read_only_folder(tmp_path) / "kpflow_template"
    with pytest.raises(SystemExit) as stop:
        main(["reach_task", str(dest)])
    err = capsys.readouterr().err
    assert stop.value.code == 1 and err.strip().splitlines()[1:] == [
        "(set KPFLOW_TRACEBACK=1 for the full traceback)"
    ], err
    assert re.match(
        rf"error: {dest} could not be written \((Permission denied|Operation not permitted|Read-only file system)\), so nothing was copied",
        err,
    ), err
    assert not dest.exists()


def test_connect_without_a_server_fails_in_one_line():
    done = subprocess.run([sys.executable, "-m", "kpflow.examples.connect", "--uri", "ws://127.0.0.1:9", "--wait", "0"],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 1 and done.stderr.startswith(
        "error: ConnectionError: no policy server at ws://127.0.0.1:9"
    ), done.stderr
    assert "Traceback" not in done.stderr
