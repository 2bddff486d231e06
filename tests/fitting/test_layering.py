"""The fitting package's layering (issue 51): no import circle among its modules, at module level or inside a
function, and the results and their selection never import presentation (the report, the headline, figures).

The graph is read from the source (every ``import`` statement, wherever it is), so a circle hidden by a
function-level import shows here even though each module imports on its own (tests/test_imports.py)."""

from __future__ import annotations

import ast
from pathlib import Path

FITTING = Path(__file__).resolve().parents[2] / "src" / "velab" / "fitting"
PRESENTATION = {"report", "headline", "plots", "campaign"}


def imports_of(path: Path) -> set[str]:
    """The velab.fitting modules that ``path`` imports anywhere in its body."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.module.startswith("velab.fitting."):
                out.add(node.module.split(".")[2])
            elif node.module == "velab.fitting":
                out.update(a.name for a in node.names if (FITTING / f"{a.name}.py").exists())
        elif isinstance(node, ast.Import):
            out.update(a.name.split(".")[2] for a in node.names if a.name.startswith("velab.fitting."))
    out.discard(path.stem)
    return out


def graph() -> dict[str, set[str]]:
    return {f.stem: imports_of(f) for f in sorted(FITTING.glob("*.py")) if f.stem != "__init__"}


def circles(g: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in g.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in g:
        if v not in index:
            visit(v)
    return found


def reachable(g: dict[str, set[str]], start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        for w in g.get(todo.pop(), ()):
            if w not in seen:
                seen.add(w)
                todo.append(w)
    return seen


def test_the_fitting_package_has_no_import_circle():
    assert circles(graph()) == []


def test_the_circle_finder_finds_a_circle_hidden_in_a_function():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert circles(g) == [["a", "b", "c"]]


def test_results_and_selection_never_import_presentation():
    g = graph()
    for module in ("results", "selection", "stats", "adequacy", "creep"):
        assert not reachable(g, module) & PRESENTATION, (module, reachable(g, module) & PRESENTATION)
