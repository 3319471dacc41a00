"""No module of point_gn_ros is in an import cycle.

Every import counts: module level, inside functions and methods, and under
`if TYPE_CHECKING:`. The graph is built from the source (ast), so an import that never runs
in a test still counts.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = 'point_gn_ros'
ROOT = Path(__file__).resolve().parents[2] / PACKAGE


def _modules() -> dict[str, Path]:
    """Dotted module name -> source file, for every module of the package."""
    out = {}
    for path in sorted(ROOT.rglob('*.py')):
        parts = list(path.relative_to(ROOT.parent).with_suffix('').parts)
        if parts[-1] == '__init__':
            parts.pop()
        out['.'.join(parts)] = path
    return out


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The package module `name` refers to (its longest prefix that is a module), or None."""
    while name:
        if name in modules:
            return name
        name = name.rpartition('.')[0]
    return None


def _imports(module: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package modules `module` imports anywhere in its source."""
    is_package = path.name == '__init__.py'
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                pkg = module.split('.') if is_package else module.split('.')[:-1]
                pkg = pkg[:len(pkg) - (node.level - 1)]
                base = '.'.join([*pkg, base] if base else pkg)
            # `from pkg import mod` imports the submodule pkg.mod where there is one
            targets = [f'{base}.{a.name}' if f'{base}.{a.name}' in modules else base
                       for a in node.names]
        else:
            continue
        for t in targets:
            hit = _resolve(t, modules) if t.startswith(PACKAGE) else None
            if hit is not None and hit != module:
                out.add(hit)
    return out


def import_graph() -> dict[str, set[str]]:
    modules = _modules()
    return {m: _imports(m, p, modules) for m, p in modules.items()}


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components (iterative), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    comp = []
                    while True:
                        m = stack.pop()
                        on_stack.discard(m)
                        comp.append(m)
                        if m == node:
                            break
                    out.append(sorted(comp))
    return out


def _a_cycle(component: list[str], graph: dict[str, set[str]]) -> list[str]:
    """One cycle through the component's first module, for the failure message."""
    members, start = set(component), component[0]
    paths = {start: [start]}
    frontier = [start]
    while frontier:
        nxt = []
        for m in frontier:
            for c in sorted(graph[m] & members):
                if c == start:
                    return [*paths[m], start]
                if c not in paths:
                    paths[c] = [*paths[m], c]
                    nxt.append(c)
        frontier = nxt
    return component


def test_graph_sees_the_package() -> None:
    graph = import_graph()
    assert f'{PACKAGE}.cli' in graph and len(graph) > 50
    # function-level and TYPE_CHECKING imports are edges too
    assert any(graph.values())


def test_cycle_detection_finds_a_cycle() -> None:
    graph = {'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}
    comps = [c for c in strongly_connected(graph) if len(c) > 1]
    assert comps == [['a', 'b', 'c']]
    assert _a_cycle(comps[0], graph) == ['a', 'b', 'c', 'a']


def test_relative_and_function_level_imports_are_edges(tmp_path: Path) -> None:
    src = ('from typing import TYPE_CHECKING\n'
           'if TYPE_CHECKING:\n    from point_gn_ros.errors import BankError\n'
           'def f():\n    from point_gn_ros import cli\n')
    path = tmp_path / 'm.py'
    path.write_text(src)
    modules = _modules()
    assert _imports('point_gn_ros.x', path, modules) == {'point_gn_ros.errors',
                                                          'point_gn_ros.cli'}


def test_no_import_cycles() -> None:
    graph = import_graph()
    cycles = [_a_cycle(c, graph) for c in strongly_connected(graph) if len(c) > 1]
    assert not cycles, 'import cycles:\n' + '\n'.join(' -> '.join(c) for c in cycles)
