"""No import cycle between silo_agent's packages: each one can be read, tested and replaced
from the bottom up (reconstruction below detection, both below the analysis that runs them).

Every import counts: inside functions (still a dependency when it runs) and under
`if TYPE_CHECKING:` (a type one package names is part of what it depends on; a cycle hidden
there is a layer that knows too much)."""

from __future__ import annotations

import ast
from pathlib import Path

import silo_agent

ROOT = Path(silo_agent.__file__).parent


def _unit(module: str) -> str:
    """The package or top-level module of silo_agent that `module` belongs to (a name imported
    from silo_agent itself, such as `__version__`, belongs to silo_agent)."""
    parts = module.split(".")
    if len(parts) < 2 or not ((ROOT / parts[1]).is_dir() or (ROOT / f"{parts[1]}.py").is_file()):
        return "silo_agent"
    return ".".join(parts[:2])


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(tree: ast.AST, package: str) -> set[str]:
    """Absolute names of the silo_agent modules imported by `tree` (`package`: for `from .`)."""
    found: set[str] = set()
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
        stack.extend(ast.iter_child_nodes(node))
    return {name for name in found if name.startswith("silo_agent.")}


def package_graph() -> dict[str, set[str]]:
    """unit -> the other units it imports, over every module under silo_agent/."""
    graph: dict[str, set[str]] = {}
    for path in sorted(ROOT.rglob("*.py")):
        name = _module_name(path)
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        unit = _unit(name)
        targets = {_unit(imported) for imported in _imports(ast.parse(path.read_text()), package)}
        graph.setdefault(unit, set()).update(targets - {unit, "silo_agent"})
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of `graph` as a path that returns to its start, or None (depth-first search)."""
    done: set[str] = set()
    for start in sorted(graph):
        path: list[str] = []
        on_path: set[str] = set()
        stack: list[tuple[str, list[str]]] = [(start, sorted(graph.get(start, ())))]
        if start in done:
            continue
        path.append(start)
        on_path.add(start)
        while stack:
            node, todo = stack[-1]
            if not todo:
                stack.pop()
                path.pop()
                on_path.discard(node)
                done.add(node)
                continue
            child = todo.pop()
            if child in on_path:
                return [*path[path.index(child) :], child]
            if child not in done:
                stack.append((child, sorted(graph.get(child, ()))))
                path.append(child)
                on_path.add(child)
    return None


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_the_graph_sees_imports_inside_functions() -> None:
    tree = ast.parse("def f():\n    from silo_agent.detect import analyse\n")
    assert _imports(tree, "silo_agent.reconstruct") == {
        "silo_agent.detect",
        "silo_agent.detect.analyse",
    }


def test_the_graph_sees_imports_for_type_checking() -> None:
    tree = ast.parse(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from silo_agent.detect.piles import Pile\n"
    )
    assert _imports(tree, "silo_agent.reconstruct") == {
        "silo_agent.detect.piles",
        "silo_agent.detect.piles.Pile",
    }


def test_no_import_cycle_between_packages() -> None:
    graph = package_graph()
    assert "silo_agent.reconstruct" in graph and "silo_agent.detect" in graph
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])
