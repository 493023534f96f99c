"""Layering: the generic packages import nothing task-specific. No module of kpflow/maps, kpflow/policies,
kpflow/serving, kpflow/utils, kpflow/data, kpflow/transport.py or
kpflow/rotations.py imports ``kpflow.tasks.<anything>`` (the task contract is ``kpflow.core``, below them): every
``import`` statement of the file counts (those inside functions too), relative ones resolved against its package."""

import ast
from pathlib import Path

import pytest

KPFLOW = Path(__file__).resolve().parents[1] / "kpflow"
GENERIC = ["geometry", "maps", "policies", "serving", "utils", "data", "transport.py", "trajectory.py"]


def module_name(path: Path) -> str:
    parts = path.relative_to(KPFLOW.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def is_module(name: str) -> bool:
    path = KPFLOW.parent.joinpath(*name.split("."))
    return path.is_dir() or path.with_suffix(".py").is_file()


def imported(source: str, module: str, is_package: bool = False) -> list[str]:
    """The modules a file's ``import`` statements name (``module``: the file's dotted name, relative imports resolved
    against its package): ``from P import n`` names the module ``P.n`` where there is one (``from kpflow.tasks import
    base``), else ``P``."""
    package = module.split(".") if is_package else module.split(".")[:-1]
    names = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            target = ".".join(base + ([node.module] if node.module else []))
            names += [f"{target}.{a.name}" if is_module(f"{target}.{a.name}") else target for a in node.names]
    return names


def task_imports(names: list[str]) -> list[str]:
    """Of the imported modules, those of ``kpflow.tasks``."""
    return sorted({n for n in names if n == "kpflow.tasks" or n.startswith("kpflow.tasks.")})


def generic_files() -> list[Path]:
    files = []
    for entry in GENERIC:
        path = KPFLOW / entry
        files += [path] if path.is_file() else sorted(path.rglob("*.py"))
    return files


def test_the_generic_packages_are_all_there():
    assert all((KPFLOW / entry).exists() for entry in GENERIC)
    assert len(generic_files()) > 50


def test_the_import_reader_resolves_relative_imports():
    source = (
        "from ..tasks.pusht.geometry import N_KEYPOINTS\nfrom ..tasks.base import Segment\nimport kpflow.tasks.suite.task\n"
        "from kpflow.tasks import base, frames\nfrom .. import tasks\nfrom . import kcfm\n"
        "def f():\n    from kpflow.tasks.arm.motion import interpolate\n"
    )
    names = imported(source, "kpflow.policies.example")
    assert "kpflow.policies.kcfm" in names and "kpflow.tasks.base" in names
    assert task_imports(names) == [
        "kpflow.tasks", "kpflow.tasks.arm.motion", "kpflow.tasks.base", "kpflow.tasks.frames", "kpflow.tasks.pusht.geometry",
        "kpflow.tasks.suite.task",
    ]  # fmt: skip
    assert imported("from .base import X\n", "kpflow.maps", is_package=True) == ["kpflow.maps.base"]


@pytest.mark.parametrize("path", generic_files(), ids=lambda p: str(p.relative_to(KPFLOW)))
def test_generic_modules_import_no_task(path):
    names = imported(path.read_text(), module_name(path), path.name == "__init__.py")
    assert not task_imports(names), (
        f"{path.relative_to(KPFLOW.parent)} imports {task_imports(names)} (the task contract is kpflow.core: import it from there)"
    )
