"""The package's import graph, rebuilt from the source: every import points down the layer stack of
docs/architecture.md (a module may import its own layer or any lower one, never a higher one)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "kpflow"

# Lowest first. A module's layer is that of its first dotted part under kpflow (kpflow.tasks.pusht.env -> tasks).
LAYERS = [
    {"utils"},
    {"geometry"},  # the one rigid fit, rotations, planar angles: below every map
    {"maps"},
    {"transport", "trajectory"},
    {"core"},  # the contracts: Policy, PolicyLayout, ClosedLoop, phases, symmetries, Task, the closed-loop rollout
    {"vision"},
    {
        "data"
    },  # generic: episodes on disk, chunks, source indices; what one task collects or imports lives in its folder
    {"tasks"},
    {"policies"},
    {"eval", "serving", "generation"},  # generation: segment transport and whole datasets, beside evaluation
    {"cli", "conf", "examples", "__init__"},  # the commands (kpflow/cli/), the installed examples and the front door
]
LEVEL = {name: level for level, names in enumerate(LAYERS) for name in names}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> set[str]:
    """The kpflow modules ``path`` imports (absolute names; relative imports resolved)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            found.add(target)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return {t for t in found if t == "kpflow" or t.startswith("kpflow.")}


def layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def import_graph() -> dict[str, set[str]]:
    return {module_name(p): imports(p) for p in sorted(PACKAGE.rglob("*.py"))}


def test_every_module_has_a_layer():
    assert {layer(m) for m in import_graph()} <= set(LEVEL), (
        "a new top-level module: give it a layer here and in docs/architecture.md"
    )


def test_no_import_points_up_the_stack():
    upward = [
        f"{a} ({layer(a)}) imports {b} ({layer(b)})"
        for a, targets in import_graph().items()
        for b in targets
        if LEVEL[layer(b)] > LEVEL[layer(a)]
    ]
    assert not upward, "upward imports:\n" + "\n".join(upward)


def test_the_checker_sees_relative_and_absolute_imports():
    probe = PACKAGE / "tasks" / "pusht" / "env.py"
    assert "kpflow.tasks.pusht.physics" in imports(probe)
    assert any(t.startswith("kpflow.data") for t in imports(PACKAGE / "tasks" / "pusht" / "teleop.py"))
