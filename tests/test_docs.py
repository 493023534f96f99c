"""The documentation site: it builds with ``mkdocs build --strict``, every tutorial's code runs as written, and every
file under kpflow/examples/ (the examples installed with kpflow) is run by some test.

A tested page (docs/tutorials/*.md, docs/quickstart.md, and README.md's python blocks) runs as one Python script made
of its fenced ``python`` blocks in page order, each ``bash`` block running at its place with ``bash -euo pipefail -c``,
in a fresh folder holding a link ``release`` to the repository's. ``--8<-- "path[:section]"`` lines
(pymdownx.snippets) are replaced by what they include; ``text`` and ``console`` blocks (and any other language) are
shown, never run. Commands find the venv's ``kpflow-*`` scripts first on PATH.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from tests.helpers import child_env

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
EXAMPLES = ROOT / "kpflow" / "examples"
TEMPLATES = EXAMPLES / "templates"  # project folders that `kpflow-example NAME DIR` copies
BIN = Path(sys.executable).parent

# pages whose code takes more than ~20 s on 2 cores (marked slow: `make test-fast` leaves them out), and why
SLOW = {
    "quickstart": "collects 35 Push-T demonstrations and evaluates 9 episodes (about a minute)",
}
# the longest pages run from files of their own (tests/test_tutorial_*.py), so that the suite's two workers share them
OWN_FILE = {
    "own-data": "trains, evaluates and serves a policy",
    "own-task": "collects, trains, evaluates and serves on a task of its own",
    "generate": "generates robosuite demonstrations (MuJoCo)",
    "mimicgen-benchmark": "generates in MimicGen's D1, trains and evaluates a robosuite policy",
    "pusht-human": "imports the human Push-T dataset, trains and evaluates a K-CFM",
}
# examples run directly (not included in a page) that take more than ~20 s, and why
SLOW_EXAMPLES: dict[str, str] = {}

ENV = {
    "OMP_NUM_THREADS": "1",
    "MPLBACKEND": "Agg",
    "WANDB_MODE": "offline",
    "NO_MKDOCS_2_WARNING": "1",
}


FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})[ \t]*\{?[ \t]*\.?(?P<lang>[\w+-]*)")
SNIPPET = re.compile(r'^(?P<indent>[ \t]*)-{1,}8<-{1,}[ \t]+"(?P<spec>[^"]+)"[ \t]*$')
SECTION_MARK = re.compile(r"-{1,}8<-{1,}[ \t]*\[[ \t]*(start|end)[ \t]*:[ \t]*([a-z][-_0-9a-z]*)[ \t]*\]")


def snippet_lines(spec: str) -> list[str]:
    """What ``--8<-- "spec"`` includes: a file (relative to the repository), ``file:section`` or ``file:start:end``."""
    path, section, lines = spec, None, None
    if m := re.fullmatch(r"(.+?):(\d*):(\d*)", spec):
        path, lines = m[1], (int(m[2] or 1), int(m[3]) if m[3] else None)
    elif (m := re.fullmatch(r"(.+):([a-z][-_0-9a-z]*)", spec)) and not (ROOT / spec).exists():
        path, section = m[1], m[2]
    text = (ROOT / path).read_text().splitlines()
    if lines:
        text = text[lines[0] - 1 : lines[1]]
    if section:
        inside, kept, found = False, [], False
        for line in text:
            if mark := SECTION_MARK.search(line):
                if mark[2] == section:
                    inside, found = mark[1] == "start", True
                continue
            if inside:
                kept.append(line)
        assert found, f"--8<-- {spec!r}: no section {section!r} in {path}"
        text = kept
    return [line for line in text if not SECTION_MARK.search(line)]


def code_blocks(text: str) -> list[tuple[str, str, int]]:
    """The fenced blocks of a Markdown page: (language, code with snippets expanded, line number), in page order."""
    blocks, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence, start, body = m["indent"], m["fence"], i + 1, []
        i += 1
        while i < len(lines) and not lines[i].strip().startswith(fence):
            line = lines[i][len(indent) :] if lines[i].startswith(indent) else lines[i].lstrip()
            if s := SNIPPET.match(line):
                body += [s["indent"] + x if x else x for x in snippet_lines(s["spec"])]
            else:
                body.append(line)
            i += 1
        i += 1
        blocks.append((m["lang"].lower(), "\n".join(body) + "\n", start))
    return blocks


def included_files(text: str) -> set[Path]:
    """Files a page includes with ``--8<--`` inside its fenced blocks."""
    return {
        (ROOT / re.split(r":(?=[a-z0-9])", s["spec"].strip())[0]).resolve()
        for line in text.splitlines()
        if (s := SNIPPET.match(line.strip()))
    }


def page_script(page: Path) -> str:
    """One Python script for a page: its python blocks as they are, its bash blocks as calls at their places."""
    readme = page.name == "README.md"
    parts = [
        "import os as _os, subprocess as _subprocess, sys as _sys\n",
        "def _bash(code, where):\n"
        "    done = _subprocess.run(['bash', '-euo', 'pipefail', '-c', code])\n"
        "    if done.returncode:\n"
        "        _sys.exit(f'the bash block at {where} exited with {done.returncode}')\n",
    ]
    for lang, code, line in code_blocks(page.read_text()):
        where = f"{page.relative_to(ROOT)}:{line}"
        if lang in ("python", "py"):
            parts.append(f"# ---- python block at {where}\n{code}")
        elif lang == "bash" and not readme:  # README's commands are make targets and long runs: python blocks only
            parts.append(f"# ---- bash block at {where}\n_bash({code!r}, {where!r})\n")
    return "\n".join(parts)


def run_in_scratch(args: list[str], folder: Path, timeout: int) -> tuple[int, str]:
    """Run ``args`` in ``folder`` (given a link to release/) with the docs' environment; the exit code
    and the output. The run is a session of its own, ended as a whole afterwards, so that a server a page started in
    the background and did not stop cannot outlive it (and its output goes to a file, which it cannot hold open)."""
    if (ROOT / "release").exists() and not (folder / "release").exists():
        (folder / "release").symlink_to(ROOT / "release")
    env = child_env(**ENV, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    log = folder / "output.log"
    with log.open("w") as out:
        proc = subprocess.Popen(args, cwd=folder, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            code = proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            code = f"timeout after {timeout} s"
        finally:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.wait()
    return code, log.read_text()[-8000:]


def pages_under_test() -> list[Path]:
    return sorted((DOCS / "tutorials").glob("*.md")) + [DOCS / "quickstart.md", ROOT / "README.md"]


def page_id(page: Path) -> str:
    return page.stem


def marked(page: Path):
    return pytest.param(page, id=page_id(page), marks=[pytest.mark.slow] if page_id(page) in SLOW else [])


def exercised_by_pages() -> tuple[set[Path], str]:
    """Files the tested pages include, and the text of the code those pages run (commands may name examples)."""
    included, run_text = set(), []
    for page in pages_under_test():
        if page.exists():
            text = page.read_text()
            included |= included_files(text)
            run_text += [code for lang, code, _ in code_blocks(text) if lang in ("python", "py", "bash")]
    return included, "\n".join(run_text)


def example_files() -> list[Path]:
    """The examples' files: scripts and template files (kpflow/examples/__init__.py, the command ``kpflow-example``
    itself, is tests/test_examples.py's)."""
    return sorted(
        p for p in EXAMPLES.rglob("*") if p.is_file() and "__pycache__" not in p.parts and p != EXAMPLES / "__init__.py"
    )


def module_of(path: Path) -> str:
    """The dotted module of a script under kpflow/examples/ (``kpflow.examples.connect``)."""
    return ".".join(path.relative_to(ROOT).with_suffix("").parts)


def console_scripts() -> dict[str, str]:
    """pyproject.toml's console scripts: module -> command (``kpflow.examples.connect`` -> ``kpflow-connect``)."""
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    return {target.split(":")[0]: name for name, target in scripts.items()}


def named_by(path: Path, run_text: str) -> bool:
    """Whether the pages' code names ``path``: a template's file by copying its template (``kpflow-example NAME``), a
    script by its module (``python -m kpflow.examples.NAME``), its console script or its path."""
    if path.is_relative_to(TEMPLATES):
        template = path.relative_to(TEMPLATES).parts[0]
        return re.search(rf"kpflow-example\s+{template}\b", run_text) is not None
    module = module_of(path)
    command = console_scripts().get(module)
    return (
        module in run_text
        or str(path.relative_to(ROOT)) in run_text
        or (command is not None and re.search(rf"{command}\b", run_text) is not None)
    )


def examples_to_run_directly() -> list[Path]:
    included, run_text = exercised_by_pages()
    return [
        p for p in example_files() if p.suffix == ".py" and p.resolve() not in included and not named_by(p, run_text)
    ]


def test_site_builds_strict(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"), "-d", str(tmp_path / "site")],
        cwd=ROOT, env=child_env(**ENV), capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-5000:] + done.stderr[-5000:]
    assert (tmp_path / "site" / "reference" / "maps" / "index.html").exists()
    assert (tmp_path / "site" / "results" / "pusht_table1" / "index.html").exists()


def check_page(page: Path, folder: Path) -> None:
    """Run ``page``'s code (module docstring) in ``folder``; fail with its output unless it exits 0."""
    script = folder / f"{page.stem}_page.py"
    script.write_text(page_script(page))
    code, output = run_in_scratch([sys.executable, str(script)], folder, timeout=1800)
    assert code == 0, f"{page.relative_to(ROOT)} (script {script}): {code}\n{output}"


@pytest.mark.parametrize("page", [marked(p) for p in pages_under_test() if page_id(p) not in OWN_FILE])
def test_page_code_runs(page: Path, tmp_path):
    check_page(page, tmp_path)


def test_the_long_pages_run_from_their_own_files():
    for name in OWN_FILE:
        assert (
            f'check_page(DOCS / "tutorials" / "{name}.md"'
            in (ROOT / "tests" / f"test_tutorial_{name.replace('-', '_')}.py").read_text()
        )


@pytest.mark.parametrize(
    "example",
    [
        pytest.param(p, id=str(p.relative_to(EXAMPLES)), marks=[pytest.mark.slow] if p.name in SLOW_EXAMPLES else [])
        for p in examples_to_run_directly()
    ],
)
def test_example_runs(example: Path, tmp_path):
    """A script of kpflow/examples/ runs as ``python -m kpflow.examples.<name>``; in a template, a script runs as
    ``python <file>`` and a module of a package (a folder with ``__init__.py``) is imported, from the folder above
    its package."""
    top = example.parent
    while (top / "__init__.py").exists():
        top = top.parent
    if not example.is_relative_to(TEMPLATES):
        args = [sys.executable, "-m", module_of(example)]
    elif top == example.parent:
        args = [sys.executable, str(example)]
    else:
        dotted = ".".join(example.relative_to(top).with_suffix("").parts).removesuffix(".__init__")
        args = [sys.executable, "-c", f"import sys; sys.path.insert(0, {str(top)!r}); import {dotted}"]
    code, output = run_in_scratch(args, tmp_path, timeout=1800)
    assert code == 0, f"{example.relative_to(ROOT)}: {code}\n{output}"


def test_every_example_is_run():
    """A .py under kpflow/examples/ is included in a tested page, named by its code or run directly above; any other
    file (a template's config) must be included or named by a tested page's code (its template copied)."""
    included, run_text = exercised_by_pages()
    unused = [
        str(p.relative_to(ROOT))
        for p in example_files()
        if p.suffix != ".py" and p.resolve() not in included and not named_by(p, run_text)
    ]
    assert not unused, f"files under kpflow/examples/ that no tested page uses: {unused}"
    assert {p.name for p in EXAMPLES.glob("*.py")} >= {"connect.py", "train_on_store.py", "transport_trajectory.py"}
    assert named_by(EXAMPLES / "connect.py", "kpflow-connect --uri ws://x") and not named_by(
        EXAMPLES / "connect.py", "kpflow-connected"
    )
    assert named_by(TEMPLATES / "reach_task" / "drive.py", "kpflow-example reach_task my_project")


def test_snippet_parsing(tmp_path):
    """The test's reading of pages: fences (also indented, in admonitions), languages, includes and sections."""
    page = (
        "# t\n\n```python\nx = 1\n```\n\n!!! note\n    ```bash\n    echo hi\n    ```\n\n```text\nnot run\n```\n\n"
        '```python\n--8<-- "kpflow/examples/transport_trajectory.py:fit"\n```\n'
    )
    blocks = code_blocks(page)
    assert [b[0] for b in blocks] == ["python", "bash", "text", "python"]
    assert blocks[1][1] == "echo hi\n"
    assert "ilwr = ILWRMap().fit(source, target)" in blocks[3][1] and "8<" not in blocks[3][1]
    assert included_files(page) == {(EXAMPLES / "transport_trajectory.py").resolve()}
    whole = "".join(snippet_lines("kpflow/examples/transport_trajectory.py"))
    assert "8<" not in whole and "transport_trajectory(" in whole
