"""The package's import rule (docs/ARCHITECTURE.md, Layers), read from the source files.

The core's layers import only themselves and the layers below them; the core imports nothing
of the package outside it and nothing of ROS; no module imports another through a cycle, and
an import inside a function counts like any other, so none can dodge a cycle.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "csam_ros"

# each layer of csam_ros.core and the layers it may import (itself included)
LAYERS: dict[str, set[str]] = {
    "model": {"model"},
    "sam": {"model", "sam"},
    "smoothing": {"model", "sam", "smoothing"},
    "joining": {"model", "sam", "smoothing", "joining"},
    "exchange": {"model", "sam", "smoothing", "joining", "exchange"},
    "merging": {"model", "sam", "smoothing", "joining", "exchange", "merging"},
    "truth": {"model", "sam", "smoothing", "joining", "truth"},
}
# the package's parts outside the core's layers, in order: each imports only parts before it
# (or itself); ``csam_ros`` is the package's own __init__
PARTS = [
    "csam_ros",
    "closing",
    "forked",
    "core",
    "bag",
    "datasets",
    "testing",
    "ros",
    "figures",
    "solve_process",
    "message_process",
    "nodes",
    "run",
    "cli",
    "bench",
]
ROS_MODULES = (
    "rclpy",
    "rosidl",
    "rosbags",
    "csam_msgs",
    "builtin_interfaces",
    "std_msgs",
    "tf2_msgs",
    "vision_msgs",
)


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path, modules: set[str]) -> Iterator[tuple[str, int]]:
    """Every module ``path`` imports, anywhere in the file, with its line: for ``from a import
    b`` the submodule ``a.b`` where that is a module of the package, else ``a``."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                name = module_name(path)
                package = name if path.name == "__init__.py" else name.rpartition(".")[0]
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                yield (sub if sub in modules else base), node.lineno


def source_files() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def import_graph() -> dict[str, set[str]]:
    files = source_files()
    modules = {module_name(p) for p in files}
    graph: dict[str, set[str]] = {}
    for path in files:
        name = module_name(path)
        graph[name] = {m for m, _ in imported_modules(path, modules) if m in modules and m != name}
    return graph


def layer_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[2] if len(parts) > 2 and parts[1] == "core" else None


def test_every_core_module_is_in_a_layer() -> None:
    for path in (PACKAGE / "core").rglob("*.py"):
        if path.parent != PACKAGE / "core":
            assert layer_of(module_name(path)) in LAYERS, path


@pytest.mark.parametrize("path", source_files(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_the_core_imports_only_its_own_layers_and_no_ros(path: Path) -> None:
    name = module_name(path)
    if not name.startswith("csam_ros.core"):
        return
    layer = layer_of(name)
    modules = {module_name(p) for p in source_files()}
    for imported, line in imported_modules(path, modules):
        where = f"{path.relative_to(PACKAGE)}:{line} imports {imported}"
        assert not imported.startswith(ROS_MODULES), where
        if imported == "csam_ros.core" or not imported.startswith("csam_ros"):
            continue
        assert imported.startswith("csam_ros.core."), f"{where}: outside the core"
        if layer is not None:
            assert layer_of(imported) in LAYERS[layer], f"{where}: above layer {layer!r}"


def part_of(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def test_every_part_of_the_package_is_in_the_order() -> None:
    assert {part_of(m) for m in import_graph()} <= set(PARTS)


def test_each_part_imports_only_the_parts_before_it() -> None:
    upward = [
        f"{a} imports {b}"
        for a, imported in import_graph().items()
        for b in imported
        if PARTS.index(part_of(b)) > PARTS.index(part_of(a))
    ]
    assert not upward, "\n".join(sorted(upward))


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a path that starts and ends at the same module, or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (found := visit(start)):
            return found
    return None


def test_no_module_imports_itself_through_a_cycle() -> None:
    cycle = find_cycle(import_graph())
    assert cycle is None, " -> ".join(cycle or [])


def test_the_cycle_finder_finds_a_cycle_through_a_lazy_import(tmp_path: Path) -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None
    source = tmp_path / "lazy.py"
    source.write_text("def f():\n    from csam_ros.core.model import se2\n")
    assert ("csam_ros.core.model.se2", 2) in set(
        imported_modules(source, {"csam_ros.core.model.se2"})
    )
