"""The layers of silo_agent, bottom up, and the directions imports may take between them: each
package can be read, tested and replaced from the bottom up.

    base            leaves: atomic files, exit statuses, limits, choices, logging
    grid            the grid library: grid, height map, filters, smoothing, geometry, volume
    config          the config models
    scan            the scan types and the silo-scan/1 format
    reconstruct detect sim          the algorithms and the simulated world
    calibrate       the offline calibration tool (builds on the reconstruction's residuals)
    analysis        pure evaluation: a scan's analysis, alarms, drift
    capture storage telemetry       the edges: cameras, the audit cache, MQTT and Prometheus
    live            live height maps for robots (frames in, maps out through telemetry's codec)
    service         orchestration: the scan path, the pipeline, the daemon, batch, live control
    web             the operator's page (a companion of the daemon) and reports
    cli             the command line

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


LAYERS: dict[str, int] = {
    "silo_agent.base": 0,
    "silo_agent.grid": 1,
    "silo_agent.config": 2,
    "silo_agent.scan": 3,
    "silo_agent.reconstruct": 4,
    "silo_agent.detect": 4,
    "silo_agent.sim": 4,
    "silo_agent.calibrate": 5,
    "silo_agent.analysis": 6,
    "silo_agent.capture": 7,
    "silo_agent.storage": 7,
    "silo_agent.telemetry": 7,
    "silo_agent.live": 8,
    "silo_agent.service": 9,
    "silo_agent.web": 10,
    "silo_agent.cli": 11,
    "silo_agent.__main__": 12,
}


def test_every_package_has_a_layer() -> None:
    assert set(package_graph()) - {"silo_agent"} == set(LAYERS)


def test_imports_go_down_the_layers() -> None:
    """A unit imports only units of lower layers: no peer and no upward import, so that e.g.
    detection never reaches into the reconstruction and the domain never knows the wire."""
    wrong = [
        f"{unit} (layer {LAYERS[unit]}) imports {target} (layer {LAYERS[target]})"
        for unit, targets in package_graph().items()
        if unit in LAYERS
        for target in sorted(targets)
        if LAYERS[target] >= LAYERS[unit]
    ]
    assert wrong == []


def test_no_private_name_crosses_a_package() -> None:
    """`from silo_agent.x import _name` only inside x's own package: what another package needs
    is public."""
    crossing = []
    for path in sorted(ROOT.rglob("*.py")):
        unit = _unit(_module_name(path))
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("silo_agent."):
                private = [a.name for a in node.names if a.name.startswith("_")]
                if private and _unit(node.module or "") != unit:
                    crossing.append(f"{path.relative_to(ROOT)}: {node.module} {private}")
    assert crossing == []


def test_no_import_cycle_between_packages() -> None:
    graph = package_graph()
    assert "silo_agent.reconstruct" in graph and "silo_agent.detect" in graph
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])
