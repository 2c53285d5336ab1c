"""The package's layout: no import circles among warpcloth's own modules.

Every import counts, wherever it stands: at module level, in a function body (imported at call time) or under
``if TYPE_CHECKING:``. The package root is left out (``import warpcloth as wc``, ``from warpcloth import X``): it
re-exports the public names, and every module may use them.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "warpcloth"
# Where each package's modules live: the checkout's top-level kernels/ is installed as warpcloth.kernels.
SOURCES = {PACKAGE: ROOT / "warpcloth", f"{PACKAGE}.kernels": ROOT / "kernels"}


def modules() -> dict[str, Path]:
    """Every module of the package, by its dotted name (a package by its own name, for its ``__init__.py``)."""
    found = {}
    for prefix, root in SOURCES.items():
        for path in sorted(root.rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join([prefix, *parts])] = path
    return found


def imported(name: str, path: Path, known: set[str]) -> set[str]:
    """The package's modules that module ``name`` imports, anywhere in its source, the package root left out."""
    is_package = path.name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module
            # "from a import b": module a.b where b is a submodule, else a (b is a name a defines)
            targets = [f"{source}.{alias.name}" if f"{source}.{alias.name}" in known else source
                       for alias in node.names]
        else:
            continue
        for target in targets:
            while target and target not in known:  # "import a.b.c" of a name inside a module: its module
                target = target.rpartition(".")[0]
            if target and target != PACKAGE and target != name:
                out.add(target)
    return out


def import_graph() -> dict[str, set[str]]:
    found = modules()
    known = set(found)
    return {name: imported(name, path, known) for name, path in found.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One loop through each strongly connected group of more than one module (Tarjan's algorithm), as a list of
    modules whose last imports the first."""
    index, low, on_stack, stack, groups = {}, {}, set(), [], []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(set(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    loops = []
    for group in groups:  # a shortest path back to the group's first module, within the group
        start = min(group)
        paths = {start: [start]}
        frontier = [start]
        loop = None
        while frontier and loop is None:
            nxt = []
            for v in frontier:
                for w in sorted(graph[v] & group):
                    if w == start:
                        loop = paths[v]
                        break
                    if w not in paths:
                        paths[w] = paths[v] + [w]
                        nxt.append(w)
                if loop is not None:
                    break
            frontier = nxt
        loops.append(loop)
    return loops


def test_no_module_imports_itself_around_a_loop():
    loops = cycles(import_graph())
    assert not loops, "import circles among warpcloth's modules: " + "; ".join(
        " -> ".join([*loop, loop[0]]) for loop in loops)


def test_the_walk_sees_the_package_and_finds_loops():
    graph = import_graph()
    assert "warpcloth.tasks.control" in graph and "warpcloth.kernels.losses" in graph
    assert "warpcloth.kernels.losses" in graph["warpcloth.tasks.control"]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_imports_in_function_bodies_and_type_checking_blocks_count(tmp_path):
    (tmp_path / "a.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from p.b import X\n")
    (tmp_path / "b.py").write_text("def f():\n    from . import a\n    import p.c.d\n")
    known = {"p", "p.a", "p.b", "p.c", "p.c.d"}
    assert imported("p.a", tmp_path / "a.py", known) == {"p.b"}
    assert imported("p.b", tmp_path / "b.py", known) == {"p.a", "p.c.d"}
